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
            "{what} {i} {:?} is not finite",
            points[i]
        ))),
        None => Ok(()),
    }
}

/// Squared Euclidean distance.
#[inline(always)]
pub fn distance_squared(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)
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

/// Eigenvalues (ascending) of a symmetric 3×3 matrix, and a unit eigenvector of the
/// smallest, in closed form (`symmetric_eigenvalues3`, then
/// `smallest_eigenvector3`). About ten times faster than an iterative solver; used for
/// normals and for the surface map's plane test (which asks for the vector only when
/// the values make a plane).
pub fn symmetric_eigen3(a: &crate::na::Matrix3<f64>) -> ([f64; 3], crate::na::Vector3<f64>) {
    let values = symmetric_eigenvalues3(a);
    (values, smallest_eigenvector3(a, values[0]))
}

/// A power of two (so scaling is exact) that brings the largest entry of `a` near 1,
/// where no square or cube of an entry over- or underflows; `None` for a zero or
/// non-finite matrix.
fn unit_scale(a: &crate::na::Matrix3<f64>) -> Option<f64> {
    let largest = a.iter().fold(0.0f64, |m: f64, &x: &f64| m.max(x.abs()));
    (largest > 0.0 && largest.is_finite()).then(|| unit_power_of_two(largest))
}

/// Eigenvalues (ascending) of a symmetric 3×3 matrix. With B = (A − qI)/p (q the mean
/// eigenvalue, p their spread) the eigenvalues are q + p·x for the roots x of
/// x³ − 3x − det B, all in [−2, 2]: the smallest by Newton's method from below, the
/// other two from the remaining quadratic; where that root is (nearly) repeated, so
/// Newton crawls, the trigonometric solution instead. The normalised cubic does not
/// lose digits to a shift (eigenvalues close together far from zero) or to the
/// matrix's scale, which is taken out by a power of two first. Covariances of a
/// surface map's nodes settle in about five steps.
/// Accurate to ~1e-12 of the largest magnitude (repeated eigenvalues lose about half
/// the digits).
pub fn symmetric_eigenvalues3(a: &crate::na::Matrix3<f64>) -> [f64; 3] {
    let Some(scale) = unit_scale(a) else {
        return [a[(0, 0)], a[(1, 1)], a[(2, 2)]].map(|x| x * 0.0); // zeros, or NaN
    };
    let a = a * scale;
    let off = a[(0, 1)].powi(2) + a[(0, 2)].powi(2) + a[(1, 2)].powi(2);
    let q = a.trace() / 3.0;
    let spread =
        (a[(0, 0)] - q).powi(2) + (a[(1, 1)] - q).powi(2) + (a[(2, 2)] - q).powi(2) + 2.0 * off;
    let values = if off <= f64::MIN_POSITIVE || spread <= f64::MIN_POSITIVE {
        // Diagonal (or a multiple of the identity).
        let mut values = [a[(0, 0)], a[(1, 1)], a[(2, 2)]];
        values.sort_by(f64::total_cmp);
        values
    } else {
        let p = (spread / 6.0).sqrt();
        let inv_p = 1.0 / p;
        // det B = det(A − qI) / p³, clamped to the cubic's range against rounding.
        let c = ((a - crate::na::Matrix3::identity() * q).determinant() * (inv_p * inv_p * inv_p))
            .clamp(-2.0, 2.0);
        let [x0, x1, x2] =
            normalised_roots_by_newton(c).unwrap_or_else(|| normalised_roots_by_angle(c));
        [q + p * x0, q + p * x1, q + p * x2]
    };
    // Powers of two: the reciprocal is exact.
    values.map(|v| v * (1.0 / scale))
}

/// The roots (ascending) of x³ − 3x − c, |c| ≤ 2, the smallest by Newton's method from
/// below: left of its smallest root the cubic rises and bends down, so the steps climb
/// to the root without passing it. `None` when they have not arrived within a few
/// steps (a root repeated or nearly so).
fn normalised_roots_by_newton(c: f64) -> Option<[f64; 3]> {
    let tolerance = 4.0 * f64::EPSILON;
    // The smallest root as a function of c is increasing and convex (the inverse of
    // the concave x³ − 3x on [−2, −1]), so its tangents lie below it: start from the
    // highest of three, at x = −2, −√3 and −1.5.
    const SQRT_3: f64 = 1.732_050_807_568_877_2;
    let mut x = (-2.0 + (c + 2.0) * (1.0 / 9.0))
        .max(-SQRT_3 + c * (1.0 / 6.0))
        .max(-1.5 + (c - 1.125) * (1.0 / 3.75));
    for _ in 0..8 {
        let f = (x * x - 3.0) * x - c;
        let slope = 3.0 * (x * x - 1.0);
        if f >= 0.0 || slope <= 0.0 {
            break; // at the root, to rounding
        }
        let step = -f / slope;
        x += step;
        // Newton's error after this step is about (f''/2f')·step² = 3|x|·step²/f':
        // stop once that is below the tolerance.
        if 3.0 * x.abs() * step * step <= tolerance * slope {
            break;
        }
    }
    let f = (x * x - 3.0) * x - c;
    let slope = 3.0 * (x * x - 1.0);
    // Converged: the cubic is no longer clearly negative here (NaN fails too).
    if f < -tolerance * slope || f.is_nan() {
        return None;
    }
    // The other two: x² + x0·x + x0² − 3 = 0.
    let root = (12.0 - 3.0 * x * x).max(0.0).sqrt();
    let middle = (-x - root) / 2.0;
    let largest = (-x + root) / 2.0;
    Some([x, middle.max(x), largest.max(middle)])
}

/// The roots (ascending) of x³ − 3x − c, |c| ≤ 2, by the trigonometric solution.
fn normalised_roots_by_angle(c: f64) -> [f64; 3] {
    let phi = (c / 2.0).clamp(-1.0, 1.0).acos() / 3.0;
    // cos(φ + 2π/3) = −(cos φ + √3 sin φ) / 2: one sin_cos instead of two cosines.
    let (sin, cos) = phi.sin_cos();
    let largest = 2.0 * cos;
    let smallest = -(cos + 3f64.sqrt() * sin);
    let middle = -largest - smallest;
    [smallest, middle, largest]
}

/// A unit eigenvector of the symmetric `a` for its smallest eigenvalue `smallest`: the
/// largest cross product of two rows of A − λI (a diagonal matrix: the axis of its
/// smallest entry).
pub fn smallest_eigenvector3(
    a: &crate::na::Matrix3<f64>,
    smallest: f64,
) -> crate::na::Vector3<f64> {
    use crate::na::Vector3;
    let Some(scale) = unit_scale(a) else {
        return Vector3::x();
    };
    let (a, smallest) = (a * scale, smallest * scale);
    let off = a[(0, 1)].powi(2) + a[(0, 2)].powi(2) + a[(1, 2)].powi(2);
    if off <= f64::MIN_POSITIVE {
        let d = [a[(0, 0)], a[(1, 1)], a[(2, 2)]];
        let min = (0..3).min_by(|&i, &j| d[i].total_cmp(&d[j])).unwrap_or(0);
        let mut v = Vector3::zeros();
        v[min] = 1.0;
        return v;
    }
    let m = a - crate::na::Matrix3::identity() * smallest;
    let rows = [
        m.row(0).transpose(),
        m.row(1).transpose(),
        m.row(2).transpose(),
    ];
    let candidates = [
        rows[0].cross(&rows[1]),
        rows[0].cross(&rows[2]),
        rows[1].cross(&rows[2]),
    ];
    let best = candidates
        .iter()
        .max_by(|x, y| x.norm_squared().total_cmp(&y.norm_squared()))
        .copied()
        .unwrap_or_default();
    if best.norm_squared() > 0.0 {
        best.normalize()
    } else {
        Vector3::x()
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
    use crate::na::{Matrix3, Rotation3, SymmetricEigen, Vector3};

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

    #[test]
    fn eigen_of_random_matrices_matches_nalgebra() {
        // Both solutions of the cubic: Newton's (separated smallest root) and the
        // angle's (repeated or nearly repeated smallest root, Newton stops early);
        // eigenvalues close together far from zero (a shift), and extreme scales.
        let mut rng = crate::synthetic::Rng::new(21);
        let (mut by_newton, mut by_angle) = (0, 0);
        for i in 0..8000 {
            let base = rng.uniform(-2.0, 2.0);
            let mut d = [
                rng.uniform(0.0, 1.0),
                rng.uniform(0.0, 1.0),
                rng.uniform(0.0, 1.0),
            ];
            match i % 8 {
                0 => d[1] = d[0] * (1.0 + 1e-9 * rng.unit()), // nearly repeated
                1 => d = [0.0, d[1], d[2]],                   // singular, PSD
                2 => d = d.map(|x| x + base),                 // any signs
                3 => d = d.map(|x| 1.0 + 1e-5 * x),           // nearly isotropic
                4 => d = d.map(|x| 1e8 + 3.0 * x),            // far from zero
                5 => d = d.map(|x| 1e110 * x),                // huge
                6 => d = d.map(|x| 1e-120 * x),               // tiny
                _ => {}
            }
            let r = Rotation3::from_euler_angles(
                rng.uniform(-3.0, 3.0),
                rng.uniform(-1.5, 1.5),
                rng.uniform(-3.0, 3.0),
            );
            let a = r.matrix() * Matrix3::from_diagonal(&Vector3::from(d)) * r.matrix().transpose();
            let a = (a + a.transpose()) / 2.0;
            let scale = d.iter().fold(0.0f64, |m, x| m.max(x.abs()));
            let (q, off) = (
                a.trace() / 3.0,
                a[(0, 1)].powi(2) + a[(0, 2)].powi(2) + a[(1, 2)].powi(2),
            );
            let spread = (0..3).map(|k| (a[(k, k)] - q).powi(2)).sum::<f64>() + 2.0 * off;
            let p = (spread / 6.0).sqrt();
            let c = ((a - Matrix3::identity() * q) / p).determinant();
            match normalised_roots_by_newton(c) {
                Some(_) => by_newton += 1,
                None => by_angle += 1,
            }
            let (values, v) = symmetric_eigen3(&a);
            let mut reference: Vec<f64> = d.to_vec();
            reference.sort_by(f64::total_cmp);
            assert!(
                values[0] <= values[1] && values[1] <= values[2],
                "{i}: {values:?}"
            );
            // Repeated eigenvalues cost about sqrt(eps); the rest ~1e-12 of the largest.
            let tolerance = if i % 8 == 0 { 1e-7 } else { 1e-11 };
            for k in 0..3 {
                assert!(
                    (values[k] - reference[k]).abs() < tolerance * scale,
                    "{i}: {values:?} vs {reference:?}"
                );
            }
            if reference[1] - reference[0] > 1e-3 * scale {
                assert!((a * v - v * values[0]).norm() < 1e-7 * scale, "{i}: {d:?}");
            }
        }
        assert!(
            by_newton > 5000 && by_angle > 200,
            "{by_newton} by Newton, {by_angle} by angle"
        );
    }

    #[test]
    fn eigenvalues_close_together_keep_their_digits() {
        // The review's case: A = [[1, e, 0], [e, 1, e], [0, e, 1]] has 1 − √2·e, 1, 1 + √2·e.
        for e in [1e-5, 3e-6, 1e-8] {
            let a = Matrix3::new(1.0, e, 0.0, e, 1.0, e, 0.0, e, 1.0);
            let values = symmetric_eigenvalues3(&a);
            let want = [1.0 - 2f64.sqrt() * e, 1.0, 1.0 + 2f64.sqrt() * e];
            for k in 0..3 {
                assert!(
                    (values[k] - want[k]).abs() < 1e-14,
                    "e {e}: {values:?} vs {want:?}"
                );
            }
        }
    }

    #[test]
    fn closed_form_eigen_matches_nalgebra() {
        for (i, d) in [
            [1e-6, 1.0, 2.0],
            [0.1, 0.1, 3.0],
            [5.0, 1.0, 1.0],
            [2.0, 2.0, 2.0],
            [0.0, 1e-3, 1e-3],
        ]
        .iter()
        .enumerate()
        {
            let r = Rotation3::from_euler_angles(0.3 * i as f64, -0.7, 1.1 + i as f64);
            let a =
                r.matrix() * Matrix3::from_diagonal(&Vector3::from(*d)) * r.matrix().transpose();
            let (values, v) = symmetric_eigen3(&a);
            let mut reference: Vec<f64> =
                SymmetricEigen::new(a).eigenvalues.iter().copied().collect();
            reference.sort_by(f64::total_cmp);
            // Repeated eigenvalues cost the trigonometric solution about sqrt(eps) of accuracy.
            for k in 0..3 {
                assert!(
                    (values[k] - reference[k]).abs() < 1e-6 * reference[2].max(1.0),
                    "{values:?} vs {reference:?}"
                );
            }
            assert!((v.norm() - 1.0).abs() < 1e-9);
            if d[0] < d[1] {
                // A unique smallest eigenvalue: v is its eigenvector.
                assert!((a * v - v * values[0]).norm() < 1e-7, "{d:?}");
            }
        }
    }
}
