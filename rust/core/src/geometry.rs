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

/// Eigenvalues (ascending) of a symmetric 3×3 matrix: the smallest root of the
/// characteristic cubic by Newton's method from below, the other two from the
/// remaining quadratic; where that root is (nearly) repeated, so Newton crawls, the
/// trigonometric solution instead. Covariances of surface points have a well
/// separated smallest eigenvalue and settle in two or three steps. Accurate to ~1e-8
/// relative (repeated eigenvalues lose about half the digits).
pub fn symmetric_eigenvalues3(a: &crate::na::Matrix3<f64>) -> [f64; 3] {
    let off = a[(0, 1)].powi(2) + a[(0, 2)].powi(2) + a[(1, 2)].powi(2);
    let q = a.trace() / 3.0;
    let spread =
        (a[(0, 0)] - q).powi(2) + (a[(1, 1)] - q).powi(2) + (a[(2, 2)] - q).powi(2) + 2.0 * off;
    if off <= f64::MIN_POSITIVE || spread <= f64::MIN_POSITIVE {
        // Diagonal (or a multiple of the identity).
        let mut values = [a[(0, 0)], a[(1, 1)], a[(2, 2)]];
        values.sort_by(f64::total_cmp);
        return values;
    }
    cubic_roots_by_newton(a, q, spread).unwrap_or_else(|| cubic_roots_by_angle(a, q, spread))
}

/// A unit eigenvector of the symmetric `a` for its smallest eigenvalue `smallest`: the
/// largest cross product of two rows of A − λI (a diagonal matrix: the axis of its
/// smallest entry).
pub fn smallest_eigenvector3(
    a: &crate::na::Matrix3<f64>,
    smallest: f64,
) -> crate::na::Vector3<f64> {
    use crate::na::Vector3;
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

/// The eigenvalues of `symmetric_eigen3` from λ³ − tλ² + sλ − d (t the trace, s the
/// sum of the principal 2×2 minors, d the determinant). Left of its smallest root a
/// real-rooted cubic rises and bends down, so Newton's steps from there climb to the
/// root without passing it. `None` when they have not arrived within a few steps (a
/// root repeated or nearly so).
fn cubic_roots_by_newton(a: &crate::na::Matrix3<f64>, q: f64, spread: f64) -> Option<[f64; 3]> {
    let t = a.trace();
    let s = a[(0, 0)] * a[(1, 1)] + a[(0, 0)] * a[(2, 2)] + a[(1, 1)] * a[(2, 2)]
        - a[(0, 1)].powi(2)
        - a[(0, 2)].powi(2)
        - a[(1, 2)].powi(2);
    let d = a.determinant();
    // All roots lie within sqrt(spread) of their mean q; with t, s, d >= 0 none is
    // negative (Descartes' rule for a real-rooted cubic), so 0 is a start below them.
    let radius = spread.sqrt();
    let mut x = if t >= 0.0 && s >= 0.0 && d >= 0.0 {
        (q - radius).max(0.0)
    } else {
        q - radius
    };
    let tolerance = 4.0 * f64::EPSILON * (q.abs() + radius);
    for _ in 0..8 {
        let p = ((x - t) * x + s) * x - d;
        let slope = (3.0 * x - 2.0 * t) * x + s;
        if p >= 0.0 || slope <= 0.0 {
            break; // at the root, to rounding
        }
        let step = -p / slope;
        x += step;
        // Newton's error after this step is about (p''/2p')·step²: stop once that is
        // below the tolerance (one step fewer than waiting for a step that small).
        if (t - 3.0 * x) * step * step <= tolerance * slope {
            break;
        }
    }
    // Converged: the polynomial is no longer clearly negative here.
    let p = ((x - t) * x + s) * x - d;
    let slope = (3.0 * x - 2.0 * t) * x + s;
    if p < 0.0 && -p > slope * tolerance {
        return None;
    }
    // The other two: sum t − x, product s − x(t − x); the stable quadratic formula.
    let sum = t - x;
    let product = s - x * sum;
    let root = (sum * sum - 4.0 * product).max(0.0).sqrt();
    let (middle, largest) = if sum >= 0.0 {
        let largest = (sum + root) / 2.0;
        (
            if largest != 0.0 {
                product / largest
            } else {
                0.0
            },
            largest,
        )
    } else {
        let middle = (sum - root) / 2.0;
        (middle, if middle != 0.0 { product / middle } else { 0.0 })
    };
    Some([x, middle.max(x), largest.max(middle)])
}

/// The eigenvalues of `symmetric_eigen3` by the trigonometric solution of the cubic.
fn cubic_roots_by_angle(a: &crate::na::Matrix3<f64>, q: f64, spread: f64) -> [f64; 3] {
    let p = (spread / 6.0).sqrt();
    let b = (a - crate::na::Matrix3::identity() * q) / p;
    let r = (b.determinant() / 2.0).clamp(-1.0, 1.0);
    let phi = r.acos() / 3.0;
    // cos(φ + 2π/3) = −(cos φ + √3 sin φ) / 2: one sin_cos instead of two cosines.
    let (sin, cos) = phi.sin_cos();
    let largest = q + 2.0 * p * cos;
    let smallest = q - p * (cos + 3f64.sqrt() * sin);
    let middle = 3.0 * q - largest - smallest;
    [smallest, middle, largest]
}

/// Indices of `points` in Morton order of their position within their bounding box.
/// Queries made in this order walk the same part of a spatial index one after the
/// other (cache hits instead of a memory miss per tree level).
pub fn morton_order(points: &[[f64; 3]]) -> Vec<u32> {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for p in points {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
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
        // angle's (repeated or nearly repeated smallest root, Newton stops early).
        let mut rng = crate::synthetic::Rng::new(21);
        let (mut by_newton, mut by_angle) = (0, 0);
        for i in 0..4000 {
            let base = rng.uniform(-2.0, 2.0);
            let mut d = [
                rng.uniform(0.0, 1.0),
                rng.uniform(0.0, 1.0),
                rng.uniform(0.0, 1.0),
            ];
            match i % 4 {
                0 => d[1] = d[0] * (1.0 + 1e-9 * rng.unit()), // nearly repeated
                1 => d = [0.0, d[1], d[2]],                   // singular, PSD
                2 => d = d.map(|x| x + base),                 // any signs
                _ => {}
            }
            let r = Rotation3::from_euler_angles(
                rng.uniform(-3.0, 3.0),
                rng.uniform(-1.5, 1.5),
                rng.uniform(-3.0, 3.0),
            );
            let a = r.matrix() * Matrix3::from_diagonal(&Vector3::from(d)) * r.matrix().transpose();
            let a = (a + a.transpose()) / 2.0;
            let t = a.trace() / 3.0;
            let spread = (0..3).map(|k| (a[(k, k)] - t).powi(2)).sum::<f64>()
                + 2.0 * (a[(0, 1)].powi(2) + a[(0, 2)].powi(2) + a[(1, 2)].powi(2));
            match cubic_roots_by_newton(&a, t, spread) {
                Some(_) => by_newton += 1,
                None => by_angle += 1,
            }
            let (values, v) = symmetric_eigen3(&a);
            let mut reference: Vec<f64> =
                SymmetricEigen::new(a).eigenvalues.iter().copied().collect();
            reference.sort_by(f64::total_cmp);
            let scale = reference[0].abs().max(reference[2].abs()).max(1e-3);
            for k in 0..3 {
                assert!(
                    (values[k] - reference[k]).abs() < 1e-6 * scale,
                    "{i}: {values:?} vs {reference:?}"
                );
            }
            if reference[1] - reference[0] > 1e-3 * scale {
                assert!((a * v - v * values[0]).norm() < 1e-7 * scale, "{i}: {d:?}");
            }
        }
        assert!(
            by_newton > 2500 && by_angle > 100,
            "{by_newton} by Newton, {by_angle} by angle"
        );
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
