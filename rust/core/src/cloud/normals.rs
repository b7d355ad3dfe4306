//! Surface normals by principal component analysis of each point's neighbourhood:
//! the direction of least spread of the point and its k nearest neighbours, turned
//! to face a viewpoint (the sensor).

use super::kdtree::KdTree;
use crate::error::{Error, Result};
use crate::na::{Matrix3, Vector3};
use crate::threads;

/// Unit normals and surface variations, one per point.
pub type Normals = (Vec<[f64; 3]>, Vec<f64>);

/// Unit normals (one per point) and the surface variation λ_min / (λ0 + λ1 + λ2)
/// (0 on a perfect plane, 1/3 for isotropic scatter).
///
/// Cost: O(N log N) for the index plus, per point, the k-neighbour query (O(k log k)
/// beyond the points it visits) and O(k) for the covariance; k near N makes the
/// whole O(N²): see [`estimate_normals_interruptible`] to stop such a call.
pub fn estimate_normals(points: &[[f64; 3]], k: usize, viewpoint: [f64; 3]) -> Result<Normals> {
    let result = estimate_normals_interruptible(points, k, viewpoint, &mut || false)?;
    // Never asked to stop, so always computed.
    result.ok_or_else(|| Error::InvalidArgument("normal estimation was interrupted".into()))
}

/// [`estimate_normals`], asking `interrupt` on the calling thread every few
/// milliseconds of work (the points are processed in rounds sized by k); `Ok(None)`
/// when it asked to stop.
pub fn estimate_normals_interruptible(
    points: &[[f64; 3]],
    k: usize,
    viewpoint: [f64; 3],
    interrupt: &mut threads::Interrupt<'_>,
) -> Result<Option<Normals>> {
    if k < 2 {
        return Err(Error::InvalidArgument(format!(
            "normals need k >= 2 neighbours, got {k}"
        )));
    }
    if points.len() <= k {
        return Err(Error::InvalidArgument(format!(
            "normal estimation needs more points than k = {k} neighbours, got {}",
            points.len()
        )));
    }
    crate::geometry::check_finite(points, "point")?;
    if !viewpoint.iter().all(|c| c.is_finite()) {
        return Err(Error::InvalidArgument(format!(
            "viewpoint {viewpoint:?} is not finite"
        )));
    }
    let tree = KdTree::new(points);
    // Queries in Morton order hit the tree's memory coherently; results go back in place.
    let order = crate::geometry::morton_order(points);
    let chunk = threads::items_per_part(k, 1 << 17, 4096);
    let chunks: Vec<&[u32]> = order.chunks(chunk).collect();
    let mapped = threads::map_parts_interruptible(
        &chunks,
        |chunk| {
            let mut nn = Vec::with_capacity(k);
            chunk
                .iter()
                .map(|&i| {
                    let i = i as usize;
                    tree.knn(points[i], k, Some(i as u32), &mut nn);
                    let neighbourhood = std::iter::once(points[i])
                        .chain(nn.iter().map(|&(_, j)| points[j as usize]));
                    (
                        i,
                        normal_of(neighbourhood, nn.len() + 1, points[i], viewpoint),
                    )
                })
                .collect::<Vec<_>>()
        },
        interrupt,
    );
    let Some(parts) = mapped else {
        return Ok(None);
    };
    let mut normals = vec![[0.0; 3]; points.len()];
    let mut variation = vec![0.0; points.len()];
    for (i, (n, v)) in parts.into_iter().flatten() {
        normals[i] = n;
        variation[i] = v;
    }
    Ok(Some((normals, variation)))
}

fn normal_of(
    pts: impl Iterator<Item = [f64; 3]> + Clone,
    n: usize,
    at: [f64; 3],
    viewpoint: [f64; 3],
) -> ([f64; 3], f64) {
    let mean = pts
        .clone()
        .fold(Vector3::zeros(), |acc, p| acc + Vector3::from(p))
        / n as f64;
    let cov = pts.fold(Matrix3::zeros(), |acc, p| {
        let d = Vector3::from(p) - mean;
        acc + d * d.transpose()
    }) / n as f64;
    let (values, mut normal) = crate::eigen3::symmetric_eigen3(&cov);
    if normal.dot(&(Vector3::from(viewpoint) - Vector3::from(at))) < 0.0 {
        normal = -normal;
    }
    let total: f64 = values.iter().sum();
    let variation = if total > 0.0 {
        values[0].max(0.0) / total
    } else {
        0.0
    };
    ([normal.x, normal.y, normal.z], variation)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic::Rng;

    /// Each point's neighbours by sorting every other point, the normal from
    /// nalgebra's general eigen solver.
    fn brute_force(points: &[[f64; 3]], k: usize, viewpoint: [f64; 3]) -> Normals {
        points
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let mut others: Vec<(f64, usize)> = points
                    .iter()
                    .enumerate()
                    .filter(|&(j, _)| j != i)
                    .map(|(j, q)| (crate::geometry::distance_squared(p, q), j))
                    .collect();
                others.sort_by(|a, b| a.partial_cmp(b).unwrap());
                let hood: Vec<Vector3<f64>> = std::iter::once(*p)
                    .chain(others[..k].iter().map(|&(_, j)| points[j]))
                    .map(Vector3::from)
                    .collect();
                let mean = hood.iter().sum::<Vector3<f64>>() / hood.len() as f64;
                let cov = hood.iter().fold(Matrix3::zeros(), |a, q| {
                    a + (q - mean) * (q - mean).transpose()
                }) / hood.len() as f64;
                let eig = crate::na::SymmetricEigen::new(cov);
                let lo = (0..3)
                    .min_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]))
                    .unwrap();
                let mut n: Vector3<f64> = eig.eigenvectors.column(lo).into_owned();
                if n.dot(&(Vector3::from(viewpoint) - Vector3::from(*p))) < 0.0 {
                    n = -n;
                }
                ([n.x, n.y, n.z], eig.eigenvalues[lo] / eig.eigenvalues.sum())
            })
            .unzip()
    }

    #[test]
    fn normals_equal_brute_force_for_small_and_large_k() {
        let mut rng = Rng::new(3);
        // A wavy sheet: every neighbourhood has one clear direction of least spread.
        let points: Vec<[f64; 3]> = (0..600)
            .map(|_| {
                let (x, y) = (rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0));
                [x, y, 0.1 * (2.0 * x).sin() + rng.uniform(-0.002, 0.002)]
            })
            .collect();
        let viewpoint = [0.3, -0.2, 2.0];
        // 10 keeps the neighbours in a sorted array, 60 and 300 in a heap.
        for k in [10, 60, 300] {
            let (normals, variation) = estimate_normals(&points, k, viewpoint).unwrap();
            let (expected, expected_variation) = brute_force(&points, k, viewpoint);
            for i in 0..points.len() {
                let d = Vector3::from(normals[i]) - Vector3::from(expected[i]);
                assert!(d.norm() < 1e-6, "k = {k}, point {i}: {normals:?}");
                assert!(
                    (variation[i] - expected_variation[i]).abs() < 1e-9,
                    "k = {k}"
                );
            }
        }
    }

    #[test]
    fn an_interrupt_stops_normal_estimation() {
        let mut rng = Rng::new(4);
        let points: Vec<[f64; 3]> = (0..2000)
            .map(|_| [rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0), 0.0])
            .collect();
        crate::threads::set_local_num_threads(Some(2));
        // k = 1500: chunks of 87 points, three rounds of eight chunks.
        let mut asked = 0;
        let stopped = estimate_normals_interruptible(&points, 1500, [0.0, 0.0, 1.0], &mut || {
            asked += 1;
            true
        });
        assert_eq!(stopped, Ok(None));
        assert_eq!(asked, 1);
        let mut asked = 0;
        let done = estimate_normals_interruptible(&points, 1500, [0.0, 0.0, 1.0], &mut || {
            asked += 1;
            false
        });
        crate::threads::set_local_num_threads(None);
        assert_eq!(asked, 3);
        assert_eq!(
            done.unwrap().unwrap(),
            estimate_normals(&points, 1500, [0.0, 0.0, 1.0]).unwrap()
        );
    }
}
