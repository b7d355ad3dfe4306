//! Rigid transforms as 4×4 homogeneous matrices (`target_from_source`).

use crate::error::{Error, Result};
use crate::na::Matrix4;

/// Check that `m` is a finite rigid transform: orthonormal rotation with det +1
/// (to 1e-6) and a bottom row of (0, 0, 0, 1).
pub fn check_rigid(m: &Matrix4<f64>, name: &str) -> Result<()> {
    if !m.iter().all(|v| v.is_finite()) {
        return Err(Error::InvalidArgument(format!(
            "{name} has non-finite entries"
        )));
    }
    let bottom = [m[(3, 0)], m[(3, 1)], m[(3, 2)], m[(3, 3)]];
    if bottom != [0.0, 0.0, 0.0, 1.0] {
        return Err(Error::InvalidArgument(format!(
            "{name} must end with the row (0, 0, 0, 1), got {bottom:?}"
        )));
    }
    let r = m.fixed_view::<3, 3>(0, 0);
    let err = (r.transpose() * r - crate::na::Matrix3::identity())
        .abs()
        .max();
    if err > 1e-6 || r.determinant() < 0.0 {
        return Err(Error::InvalidArgument(format!(
            "{name} is not a rigid transform (rotation part off orthonormal by {err:.2e} or a reflection)"
        )));
    }
    Ok(())
}

/// Most cells a grid of `size` may count from the origin along an axis: beyond, the
/// cell indices of neighbouring points stop being distinct (f64 has 53 bits).
pub const MAX_CELL_INDEX: f64 = (1u64 << 50) as f64;

/// Check that finite `points` lie within [`MAX_CELL_INDEX`] cells of size `size` of
/// the origin, so that a grid of such cells tells them apart.
pub fn check_cell_range(points: &[[f64; 3]], size: f64, what: &str) -> Result<()> {
    let reach = points
        .as_flattened()
        .iter()
        .fold(0.0f64, |m, c| m.max(c.abs()));
    if reach / size > MAX_CELL_INDEX {
        return Err(Error::InvalidArgument(format!(
            "{what} {} is too small for coordinates up to {}: more than 2^50 cells from the origin",
            fmt_num(size),
            fmt_num(reach)
        )));
    }
    Ok(())
}

/// Error naming the first point (of what `what` calls them) with a NaN or infinite coordinate.
pub fn check_finite(points: &[[f64; 3]], what: &str) -> Result<()> {
    // One pass without an early exit vectorises; the search runs only on failure.
    if points
        .as_flattened()
        .iter()
        .fold(true, |ok, c| ok & c.is_finite())
    {
        return Ok(());
    }
    match points.iter().position(|p| !p.iter().all(|c| c.is_finite())) {
        Some(i) => Err(Error::InvalidArgument(format!(
            "{what} {i} {} is not finite",
            fmt_point(&points[i])
        ))),
        None => Ok(()),
    }
}

/// A number for a message, like C's `%.6g`: six significant digits, exponent notation
/// outside [1e-4, 1e6), so 1e-100 or 1e308 print as a few characters, not hundreds.
pub fn fmt_num(x: f64) -> String {
    if !x.is_finite() || x == 0.0 {
        return format!("{x}");
    }
    let exponent = x.abs().log10().floor() as i32;
    if (-4..6).contains(&exponent) {
        let decimals = (5 - exponent).max(0) as usize;
        let s = format!("{x:.decimals$}");
        if s.contains('.') {
            s.trim_end_matches('0').trim_end_matches('.').to_owned()
        } else {
            s
        }
    } else {
        let s = format!("{x:.5e}");
        match s.split_once('e') {
            Some((mantissa, exp)) if mantissa.contains('.') => {
                let mantissa = mantissa.trim_end_matches('0').trim_end_matches('.');
                format!("{mantissa}e{exp}")
            }
            _ => s,
        }
    }
}

/// A point for a message: `(x, y, z)` with [`fmt_num`]'s numbers.
pub fn fmt_point(p: &[f64; 3]) -> String {
    format!("({}, {}, {})", fmt_num(p[0]), fmt_num(p[1]), fmt_num(p[2]))
}

/// Squared Euclidean distance.
#[inline(always)]
pub fn distance_squared(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)
}

/// `a − b`.
#[inline(always)]
pub fn sub(a: &[f64; 3], b: &[f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// `a · b`.
#[inline(always)]
pub fn dot(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// `a × b`.
#[inline(always)]
pub fn cross(a: &[f64; 3], b: &[f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// Apply `m` to every point in place.
pub fn transform_points(m: &Matrix4<f64>, points: &mut [[f64; 3]]) {
    let r = m.fixed_view::<3, 3>(0, 0).into_owned();
    let t = m.fixed_view::<3, 1>(0, 3).into_owned();
    for p in points {
        let q = r * crate::na::Vector3::new(p[0], p[1], p[2]) + t;
        *p = [q.x, q.y, q.z];
    }
}

/// The componentwise minimum and maximum of the points (infinite for none).
pub fn bounds(points: &[[f64; 3]]) -> ([f64; 3], [f64; 3]) {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for p in points {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    (lo, hi)
}

/// The power of two 2^(−e) that brings a positive finite `magnitude` near 1 (2^1000 for
/// subnormals): scaling by it is exact, and keeps squares and cubes in range.
pub fn unit_power_of_two(magnitude: f64) -> f64 {
    let exponent = ((magnitude.to_bits() >> 52) as i64).clamp(23, 2045);
    f64::from_bits(((2046 - exponent) as u64) << 52)
}

/// Indices of `points` in Morton order of their position within their bounding box.
/// Queries made in this order walk the same part of a spatial index one after the
/// other (cache hits instead of a memory miss per tree level).
pub fn morton_order(points: &[[f64; 3]]) -> Vec<u32> {
    let (lo, hi) = bounds(points);
    let scale = [0, 1, 2].map(|a| {
        if hi[a] > lo[a] {
            65535.0 / (hi[a] - lo[a])
        } else {
            0.0
        }
    });
    let mut keyed: Vec<(u64, u32)> = points
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let k = [0, 1, 2].map(|a| ((p[a] - lo[a]) * scale[a]) as u16);
            (crate::octree::OcTreeKey(k).morton(), i as u32)
        })
        .collect();
    sort_keyed(&mut keyed);
    keyed.into_iter().map(|(_, i)| i).collect()
}

/// Sort `(key, index)` pairs made in input order (indices increasing) by key, equal
/// keys in input order: the order `sort_unstable` gives, by a least-significant-digit
/// radix sort on 12-bit digits of the key that skips the digits all keys share (spatial
/// codes of one scan share their high bits). 3-5× faster than a comparison sort at 15k pairs.
pub fn sort_keyed(items: &mut [(u64, u32)]) {
    const BITS: u32 = 12;
    const BUCKETS: usize = 1 << BITS;
    let n = items.len();
    if n < 512 {
        items.sort_unstable();
        return;
    }
    // The digits in which some key differs from the first: only those need a pass.
    let first = items[0].0;
    let differs = items.iter().fold(0u64, |acc, &(k, _)| acc | (k ^ first));
    let shifts: Vec<u32> = (0..64u32.div_ceil(BITS))
        .map(|d| d * BITS)
        .filter(|&shift| (differs >> shift) & (BUCKETS as u64 - 1) != 0)
        .collect();
    let digit = |key: u64, shift: u32| ((key >> shift) & (BUCKETS as u64 - 1)) as usize;
    let mut counts = vec![[0u32; BUCKETS]; shifts.len()];
    for &(k, _) in items.iter() {
        for (&shift, count) in shifts.iter().zip(counts.iter_mut()) {
            count[digit(k, shift)] += 1;
        }
    }
    let mut scratch = vec![(0u64, 0u32); n];
    let (mut src, mut dst) = (&mut items[..], &mut scratch[..]);
    let mut in_scratch = false;
    for (&shift, count) in shifts.iter().zip(counts.iter_mut()) {
        // The counts become each bucket's next slot.
        let mut sum = 0;
        for c in count.iter_mut() {
            let here = *c;
            *c = sum;
            sum += here;
        }
        for &item in src.iter() {
            let d = digit(item.0, shift);
            dst[count[d] as usize] = item;
            count[d] += 1;
        }
        std::mem::swap(&mut src, &mut dst);
        in_scratch = !in_scratch;
    }
    if in_scratch {
        items.copy_from_slice(&scratch);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_print_like_percent_six_g() {
        // The references are C's printf("%.6g") (Python's format(x, ".6g")), apart from
        // Rust's exponent spelling (no sign padding: 1e-100, not 1e-100 with two digits).
        for (x, want) in [
            (0.05, "0.05"),
            (1638.4, "1638.4"),
            (-1638.41, "-1638.41"),
            (1.0 / 3.0, "0.333333"),
            (123456.0, "123456"),
            (1234567.0, "1.23457e6"),
            (1e308, "1e308"),
            (1e-100, "1e-100"),
            (0.0001, "0.0001"),
            (0.00001234, "1.234e-5"),
            (f64::INFINITY, "inf"),
            (f64::NAN, "NaN"),
            (0.0, "0"),
        ] {
            assert_eq!(fmt_num(x), want, "{x:e}");
        }
        assert_eq!(fmt_point(&[1e300, -0.5, 2.0]), "(1e300, -0.5, 2)");
    }

    #[test]
    fn radix_sort_of_keyed_pairs_equals_comparison_sort() {
        let mut rng = crate::synthetic::Rng::new(3);
        for (n, spread) in [
            (10, 1e9),
            (600, 1e3),
            (5000, 1e15),
            (20_000, 50.0),
            (20_000, 1e12),
        ] {
            let items: Vec<(u64, u32)> = (0..n)
                .map(|i| ((rng.uniform(0.0, spread) as u64) | (7 << 50), i as u32))
                .collect();
            let mut expected = items.clone();
            expected.sort_unstable();
            let mut got = items;
            sort_keyed(&mut got);
            assert_eq!(got, expected, "n = {n}");
        }
    }
}
