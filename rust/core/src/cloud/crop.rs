//! Keep the points inside a sphere (Paper II: 1.5 m around the robot base) or a box.

use crate::error::{Error, Result};

/// Indices of the points within `radius` of `center` (boundary included).
pub fn crop_sphere(points: &[[f64; 3]], center: [f64; 3], radius: f64) -> Result<Vec<u32>> {
    if !(radius.is_finite() && radius >= 0.0 && center.iter().all(|c| c.is_finite())) {
        return Err(Error::InvalidArgument(format!(
            "crop sphere needs a finite centre and radius >= 0, got {center:?}, {radius}"
        )));
    }
    let r2 = radius * radius;
    Ok(filter(points, |p| {
        let d = [p[0] - center[0], p[1] - center[1], p[2] - center[2]];
        d[0] * d[0] + d[1] * d[1] + d[2] * d[2] <= r2
    }))
}

/// Indices of the points inside the axis-aligned box `[lo, hi]` (faces included).
pub fn crop_box(points: &[[f64; 3]], lo: [f64; 3], hi: [f64; 3]) -> Result<Vec<u32>> {
    if !(0..3).all(|a| lo[a].is_finite() && hi[a].is_finite() && lo[a] <= hi[a]) {
        return Err(Error::InvalidArgument(format!(
            "crop box needs finite corners with lo <= hi, got {lo:?}, {hi:?}"
        )));
    }
    Ok(filter(points, |p| {
        (0..3).all(|a| p[a] >= lo[a] && p[a] <= hi[a])
    }))
}

fn filter(points: &[[f64; 3]], keep: impl Fn(&[f64; 3]) -> bool) -> Vec<u32> {
    // Branch-free compaction: write every index, advance past the kept ones (faster
    // than pushing: no branch to mispredict where a crop edge crosses the rows).
    let mut kept = vec![0u32; points.len()];
    let mut n = 0;
    for (i, p) in points.iter().enumerate() {
        kept[n] = i as u32;
        n += usize::from(keep(p));
    }
    kept.truncate(n);
    kept
}
