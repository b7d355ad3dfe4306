//! Rigid 3D-3D fit of paired points (Kabsch/Umeyama without scale), plain and with
//! RANSAC. Calibration fits a camera's measured board corners to the same corners
//! placed by forward kinematics (Paper I's eye-to-hand), and the board's offset on the
//! flange the same way.

use crate::error::{Error, Result};
use crate::geometry::{check_finite, distance_squared};
use crate::na::{Matrix3, Matrix4, Vector3};
use crate::synthetic::Rng;

/// `dst_from_src` minimising Σ wᵢ |R srcᵢ + t − dstᵢ|² (weights default to 1).
///
/// Needs at least three pairs that are not all on one line (else the rotation about
/// that line is free): an error says so.
pub fn rigid_fit(
    src: &[[f64; 3]],
    dst: &[[f64; 3]],
    weights: Option<&[f64]>,
) -> Result<Matrix4<f64>> {
    check_pairs(src, dst)?;
    if let Some(w) = weights {
        if w.len() != src.len() {
            return Err(Error::InvalidArgument(format!(
                "weights must have one entry per pair ({}), got {}",
                src.len(),
                w.len()
            )));
        }
        if let Some(i) = w.iter().position(|v| !(v.is_finite() && *v >= 0.0)) {
            return Err(Error::InvalidArgument(format!(
                "weight {i} must be finite and >= 0, got {}",
                w[i]
            )));
        }
    }
    let all: Vec<usize> = (0..src.len()).collect();
    fit_subset(src, dst, weights, &all)
}

/// Outcome of `rigid_fit_ransac`.
#[derive(Debug, Clone)]
pub struct RansacFit {
    /// `dst_from_src`, refitted on all inliers of the best hypothesis.
    pub transform: Matrix4<f64>,
    /// Pairs within `threshold` of each other under `transform`.
    pub inliers: Vec<bool>,
    /// RMS distance over the inliers (metres).
    pub rmse: f64,
}

/// RANSAC around `rigid_fit`: `iterations` hypotheses from three random pairs, the
/// one with the most pairs within `threshold` wins (ties: the lower inlier error),
/// then a refit on its inliers, repeated until the inlier set stops changing.
pub fn rigid_fit_ransac(
    src: &[[f64; 3]],
    dst: &[[f64; 3]],
    threshold: f64,
    iterations: usize,
    seed: u64,
) -> Result<RansacFit> {
    rigid_fit_ransac_interruptible(src, dst, threshold, iterations, seed, &mut || false)?
        .ok_or_else(|| Error::InvalidArgument("RANSAC was interrupted".into()))
}

/// [`rigid_fit_ransac`], asking `interrupt` on the calling thread after every
/// hypothesis (one O(N) scoring pass); `Ok(None)` when it asked to stop, so however
/// many `iterations` are allowed the call can be stopped.
pub fn rigid_fit_ransac_interruptible(
    src: &[[f64; 3]],
    dst: &[[f64; 3]],
    threshold: f64,
    iterations: usize,
    seed: u64,
    interrupt: &mut crate::threads::Interrupt<'_>,
) -> Result<Option<RansacFit>> {
    check_pairs(src, dst)?;
    if !(threshold.is_finite() && threshold * threshold > 0.0) {
        return Err(Error::InvalidArgument(format!(
            "threshold must be finite and > 0, got {threshold}"
        )));
    }
    let n = src.len();
    let t2 = threshold * threshold;
    let score = |m: &Matrix4<f64>| -> (usize, f64) {
        let mut count = 0;
        let mut err = 0.0;
        for (s, d) in src.iter().zip(dst) {
            let e = distance_squared(&apply(m, s), d);
            if e <= t2 {
                count += 1;
                err += e;
            }
        }
        (count, err)
    };
    let mut rng = Rng::new(seed);
    let mut best: Option<(usize, f64, Matrix4<f64>)> = None;
    for _ in 0..iterations.max(1) {
        if interrupt() {
            return Ok(None);
        }
        let pick = [0, 1, 2].map(|_| ((rng.unit() * n as f64) as usize).min(n - 1));
        if pick[0] == pick[1] || pick[1] == pick[2] || pick[0] == pick[2] {
            continue;
        }
        let Ok(m) = fit_subset(src, dst, None, &pick) else {
            continue; // collinear sample
        };
        let (count, err) = score(&m);
        let better = match &best {
            None => true,
            Some((c, e, _)) => count > *c || (count == *c && err < *e),
        };
        if better {
            best = Some((count, err, m));
        }
    }
    let mut transform = match best {
        Some((count, _, m)) if count >= 3 => m,
        _ => rigid_fit(src, dst, None)?, // no usable sample: every pair counts
    };
    let mut inliers: Vec<bool> = Vec::new();
    for _ in 0..10 {
        let now: Vec<bool> = src
            .iter()
            .zip(dst)
            .map(|(s, d)| distance_squared(&apply(&transform, s), d) <= t2)
            .collect();
        if now == inliers {
            break;
        }
        inliers = now;
        let idx: Vec<usize> = (0..n).filter(|&i| inliers[i]).collect();
        if idx.len() < 3 {
            break;
        }
        transform = fit_subset(src, dst, None, &idx)?;
    }
    let (count, err) = score(&transform);
    let rmse = if count > 0 {
        (err / count as f64).sqrt()
    } else {
        f64::NAN
    };
    Ok(Some(RansacFit {
        transform,
        inliers,
        rmse,
    }))
}

fn check_pairs(src: &[[f64; 3]], dst: &[[f64; 3]]) -> Result<()> {
    if src.len() != dst.len() {
        return Err(Error::InvalidArgument(format!(
            "source and target must pair up, got {} and {} points",
            src.len(),
            dst.len()
        )));
    }
    if src.len() < 3 {
        return Err(Error::InvalidArgument(format!(
            "a rigid fit needs at least 3 point pairs, got {}",
            src.len()
        )));
    }
    check_finite(src, "source point")?;
    check_finite(dst, "target point")?;
    // Squared spreads of larger coordinates overflow to infinity (a NaN fit).
    let reach = src
        .iter()
        .chain(dst)
        .flatten()
        .fold(0.0f64, |m, c| m.max(c.abs()));
    if reach > 1e150 {
        return Err(Error::InvalidArgument(format!(
            "coordinates up to {reach} are too large for a rigid fit (at most 1e150)"
        )));
    }
    Ok(())
}

fn apply(m: &Matrix4<f64>, p: &[f64; 3]) -> [f64; 3] {
    let q = m.fixed_view::<3, 3>(0, 0) * Vector3::from(*p) + m.fixed_view::<3, 1>(0, 3);
    [q.x, q.y, q.z]
}

fn fit_subset(
    src: &[[f64; 3]],
    dst: &[[f64; 3]],
    weights: Option<&[f64]>,
    idx: &[usize],
) -> Result<Matrix4<f64>> {
    let w = |i: usize| weights.map_or(1.0, |w| w[i]);
    let total: f64 = idx.iter().map(|&i| w(i)).sum();
    if total.is_nan() || total <= 0.0 {
        return Err(Error::InvalidArgument("the weights sum to zero".into()));
    }
    let mut cs = Vector3::zeros();
    let mut cd = Vector3::zeros();
    for &i in idx {
        cs += w(i) * Vector3::from(src[i]);
        cd += w(i) * Vector3::from(dst[i]);
    }
    cs /= total;
    cd /= total;
    // Cross-covariance; its rank tells whether the points span more than a line.
    let mut h = Matrix3::zeros();
    let mut spread = Matrix3::zeros();
    for &i in idx {
        let s = Vector3::from(src[i]) - cs;
        let d = Vector3::from(dst[i]) - cd;
        h += w(i) * s * d.transpose();
        spread += w(i) * s * s.transpose();
    }
    let eig = spread.symmetric_eigenvalues();
    let (lo, hi) = (
        eig.iter().cloned().fold(f64::INFINITY, f64::min),
        eig.iter().cloned().fold(0.0, f64::max),
    );
    let middle = eig.sum() - lo - hi;
    if hi.is_nan() || hi <= 0.0 || middle <= 1e-12 * hi {
        return Err(Error::InvalidArgument(
            "the source points are (nearly) collinear: the rotation about their line is undetermined".into(),
        ));
    }
    let svd = h.svd(true, true);
    let (u, v_t) = (svd.u.unwrap(), svd.v_t.unwrap());
    let v = v_t.transpose();
    let mut d = Matrix3::identity();
    if (v * u.transpose()).determinant() < 0.0 {
        d[(2, 2)] = -1.0; // a reflection would fit better: take the best rotation instead
    }
    let r = v * d * u.transpose();
    let t = cd - r * cs;
    let mut m = Matrix4::identity();
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
    m.fixed_view_mut::<3, 1>(0, 3).copy_from(&t);
    Ok(m)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::na::{Rotation3, Translation3};

    fn pose(seed: u64) -> Matrix4<f64> {
        let mut rng = Rng::new(seed);
        let axis = Vector3::new(
            rng.uniform(-1.0, 1.0),
            rng.uniform(-1.0, 1.0),
            rng.uniform(-1.0, 1.0),
        );
        let r = Rotation3::from_scaled_axis(axis.normalize() * rng.uniform(-3.0, 3.0));
        let t = Translation3::new(
            rng.uniform(-2.0, 2.0),
            rng.uniform(-2.0, 2.0),
            rng.uniform(-2.0, 2.0),
        );
        (t.to_homogeneous()) * r.to_homogeneous()
    }

    fn cloud(n: usize, seed: u64) -> Vec<[f64; 3]> {
        let mut rng = Rng::new(seed);
        (0..n)
            .map(|_| {
                [
                    rng.uniform(-0.5, 0.5),
                    rng.uniform(-0.5, 0.5),
                    rng.uniform(-0.5, 0.5),
                ]
            })
            .collect()
    }

    #[test]
    fn recovers_an_exact_transform() {
        for seed in 1..20 {
            let m = pose(seed);
            let src = cloud(10, seed + 100);
            let dst: Vec<_> = src.iter().map(|p| apply(&m, p)).collect();
            let fit = rigid_fit(&src, &dst, None).unwrap();
            assert!((fit - m).abs().max() < 1e-9, "seed {seed}");
        }
    }

    #[test]
    fn planar_points_are_enough_but_a_line_is_not() {
        let m = pose(3);
        let plane: Vec<[f64; 3]> = cloud(12, 4).iter().map(|p| [p[0], p[1], 0.0]).collect();
        let dst: Vec<_> = plane.iter().map(|p| apply(&m, p)).collect();
        assert!((rigid_fit(&plane, &dst, None).unwrap() - m).abs().max() < 1e-9);
        let line: Vec<[f64; 3]> = (0..5).map(|i| [i as f64, 2.0 * i as f64, 0.0]).collect();
        let dst: Vec<_> = line.iter().map(|p| apply(&m, p)).collect();
        assert!(rigid_fit(&line, &dst, None).is_err());
    }

    #[test]
    fn ransac_ignores_outliers() {
        let m = pose(7);
        let src = cloud(60, 8);
        let mut dst: Vec<_> = src.iter().map(|p| apply(&m, p)).collect();
        for p in dst.iter_mut().step_by(4) {
            p[2] += 0.3; // 15 gross outliers
        }
        let plain = rigid_fit(&src, &dst, None).unwrap();
        assert!((plain - m).abs().max() > 1e-3);
        let fit = rigid_fit_ransac(&src, &dst, 0.01, 100, 1).unwrap();
        assert!((fit.transform - m).abs().max() < 1e-9);
        assert_eq!(fit.inliers.iter().filter(|&&b| !b).count(), 15);
        assert!(fit.rmse < 1e-9);
    }

    #[test]
    fn weights_select_pairs() {
        let m = pose(9);
        let src = cloud(8, 10);
        let mut dst: Vec<_> = src.iter().map(|p| apply(&m, p)).collect();
        dst[0][0] += 1.0;
        let mut w = vec![1.0; 8];
        w[0] = 0.0;
        assert!((rigid_fit(&src, &dst, Some(&w)).unwrap() - m).abs().max() < 1e-9);
    }

    #[test]
    fn bad_input_is_an_error() {
        let a = cloud(3, 1);
        assert!(rigid_fit(&a[..2], &a[..2], None).is_err());
        assert!(rigid_fit(&a, &a[..2], None).is_err());
        let mut b = a.clone();
        b[1][0] = f64::NAN;
        assert!(rigid_fit(&a, &b, None).is_err());
        assert!(rigid_fit_ransac(&a, &a, 0.0, 10, 0).is_err());
        assert!(rigid_fit(&a, &a, Some(&[1.0, -1.0, 1.0])).is_err());
    }

    #[test]
    fn an_interrupt_stops_ransac_between_hypotheses() {
        let src: Vec<[f64; 3]> = (0..50)
            .map(|i| {
                let t = i as f64;
                [t.sin(), (0.7 * t).cos(), 0.1 * t]
            })
            .collect();
        let dst: Vec<[f64; 3]> = src.iter().map(|p| [p[0] + 0.5, p[1], p[2]]).collect();
        let mut asked = 0;
        let stopped = rigid_fit_ransac_interruptible(&src, &dst, 0.01, 1 << 40, 0, &mut || {
            asked += 1;
            asked > 3
        })
        .unwrap();
        assert!(stopped.is_none() && asked == 4);
        let fit = rigid_fit_ransac_interruptible(&src, &dst, 0.01, 50, 0, &mut || false)
            .unwrap()
            .unwrap();
        assert!((fit.transform[(0, 3)] - 0.5).abs() < 1e-9 && fit.inliers.iter().all(|&b| b));
    }
}
