//! Point-cloud functions: depth back-projection, crop, outlier removal, voxel grid.
//! They return indices where the Python layer selects rows (colours, normals...).

use earcore_core::cloud::{self, BrownConrady, DepthFrame, Intrinsics, OutlierParams};
use numpy::{PyArray1, PyArray2, PyArrayMethods, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::convert::{numbers, points, pose, rows_to_array, vec_to_array, vector3};
use crate::errors::IntoPyResult;
use crate::interrupt::detach_interruptible;

/// Points and, per point, the index of the pixel (or input row) it came from.
type PointsAndIndex<'py> = (Bound<'py, PyArray2<f64>>, Bound<'py, PyArray1<u32>>);
/// Kept indices and a float per input point.
type IndexAndValues<'py> = (Bound<'py, PyArray1<u32>>, Bound<'py, PyArray1<f64>>);
/// A vector and a float per point.
type VectorsAndValues<'py> = (Bound<'py, PyArray2<f64>>, Bound<'py, PyArray1<f64>>);
/// A transform, an inlier mask and the inlier RMSE.
type TransformInliersRmse<'py> = (Bound<'py, PyArray2<f64>>, Bound<'py, PyArray1<bool>>, f64);
/// Centroids and optional per-voxel means.
type Centroids<'py> = (Bound<'py, PyArray2<f64>>, Option<Bound<'py, PyArray2<f64>>>);

/// (points (N, 3), pixel index (N,) uint32) of the valid pixels of a depth image.
#[pyfunction]
#[pyo3(signature = (depth, fx, fy, cx, cy, distortion=None, depth_scale=1.0, min_depth=0.0, max_depth=None, base_from_camera=None))]
#[allow(clippy::too_many_arguments)]
pub fn depth_to_points_raw<'py>(
    py: Python<'py>,
    depth: &Bound<'py, PyAny>,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    distortion: Option<&Bound<'py, PyAny>>,
    depth_scale: f64,
    min_depth: f64,
    max_depth: Option<f64>,
    base_from_camera: Option<&Bound<'py, PyAny>>,
) -> PyResult<PointsAndIndex<'py>> {
    let np = PyModule::import(py, "numpy")?;
    let depth = crate::convert::real_array(depth, "depth", "an (H, W) array of numbers")?;
    let img = np
        .call_method1("ascontiguousarray", (depth.clone(), np.getattr("float32")?))
        .map_err(|e| {
            pyo3::exceptions::PyTypeError::new_err(format!(
                "depth must be an (H, W) array of numbers: {e}"
            ))
        })?;
    let img: PyReadonlyArray2<f32> = img.extract().map_err(|_| {
        PyValueError::new_err(format!(
            "depth must be an (H, W) image, got shape {}",
            depth
                .getattr("shape")
                .and_then(|shape| shape.str().map(|s| s.to_string()))
                .unwrap_or_else(|_| "?".into())
        ))
    })?;
    let (height, width) = (img.shape()[0], img.shape()[1]);
    let lens = match distortion {
        None => None,
        Some(d) => {
            let c = numbers(d, "distortion")?;
            match c.as_slice() {
                [k1, k2, p1, p2] => Some(BrownConrady {
                    k1: *k1,
                    k2: *k2,
                    p1: *p1,
                    p2: *p2,
                    k3: 0.0,
                }),
                [k1, k2, p1, p2, k3] => Some(BrownConrady {
                    k1: *k1,
                    k2: *k2,
                    p1: *p1,
                    p2: *p2,
                    k3: *k3,
                }),
                _ => {
                    return Err(PyValueError::new_err(format!(
                        "distortion must be OpenCV's (k1, k2, p1, p2[, k3]), got {} numbers",
                        c.len()
                    )))
                }
            }
        }
    };
    let pose = base_from_camera
        .map(|p| pose(p, "base_from_camera"))
        .transpose()?;
    let depth = img.as_slice()?;
    let k = Intrinsics { fx, fy, cx, cy };
    let (pts, pixels) = py
        .detach(|| {
            let frame = DepthFrame {
                depth,
                width,
                height,
                scale: depth_scale,
            };
            cloud::depth_to_points(
                &frame,
                &k,
                lens.as_ref(),
                min_depth,
                max_depth.unwrap_or(f64::INFINITY),
                pose.as_ref(),
            )
        })
        .py()?;
    Ok((rows_to_array(py, pts)?, vec_to_array(py, pixels)))
}

/// The points inside a sphere (`center`, `radius`) or a box (`box_min`, `box_max`), and
/// their indices (the rows are copied here: numpy's `take` of them took as long as the test).
#[pyfunction]
#[pyo3(signature = (points, center=None, radius=None, box_min=None, box_max=None))]
pub fn crop_raw<'py>(
    py: Python<'py>,
    points: &Bound<'py, PyAny>,
    center: Option<&Bound<'py, PyAny>>,
    radius: Option<f64>,
    box_min: Option<&Bound<'py, PyAny>>,
    box_max: Option<&Bound<'py, PyAny>>,
) -> PyResult<PointsAndIndex<'py>> {
    let pts = self::points(points, "points")?;
    let slice = pts.as_slice()?;
    let idx = match (box_min, box_max) {
        (Some(lo), Some(hi)) => {
            let (lo, hi) = (vector3(lo, "box_min")?, vector3(hi, "box_max")?);
            py.detach(|| cloud::crop_box(slice, lo, hi)).py()?
        }
        (None, None) => {
            let c = center
                .map(|c| vector3(c, "center"))
                .transpose()?
                .unwrap_or([0.0; 3]);
            let r = radius.unwrap_or(1.5);
            py.detach(|| cloud::crop_sphere(slice, c, r)).py()?
        }
        _ => {
            return Err(PyValueError::new_err(
                "give both box_min and box_max for a box crop",
            ))
        }
    };
    let kept = py.detach(|| idx.iter().map(|&i| slice[i as usize]).collect());
    Ok((rows_to_array(py, kept)?, vec_to_array(py, idx)))
}

/// Inlier indices and every point's mean distance to its k nearest neighbours.
#[pyfunction]
#[pyo3(signature = (points, k=20, std_ratio=2.0))]
pub fn statistical_outlier_indices<'py>(
    py: Python<'py>,
    points: &Bound<'py, PyAny>,
    k: usize,
    std_ratio: f64,
) -> PyResult<IndexAndValues<'py>> {
    let pts = self::points(points, "points")?;
    let slice = pts.as_slice()?;
    let found = detach_interruptible(py, |stop| {
        cloud::statistical_outliers_interruptible(slice, OutlierParams { k, std_ratio }, stop)
    })?;
    let Some((idx, dist)) = found.py()? else {
        // Stopped only when a signal handler raised, which detach_interruptible returned.
        return Err(pyo3::exceptions::PyKeyboardInterrupt::new_err(
            "outlier removal was interrupted",
        ));
    };
    Ok((vec_to_array(py, idx), vec_to_array(py, dist)))
}

/// Voxel centroids (M, 3) and, with `values` (N, C), their per-voxel means (M, C).
#[pyfunction]
#[pyo3(signature = (points, voxel_size, values=None))]
pub fn voxel_downsample_raw<'py>(
    py: Python<'py>,
    points: &Bound<'py, PyAny>,
    voxel_size: f64,
    values: Option<&Bound<'py, PyAny>>,
) -> PyResult<Centroids<'py>> {
    let pts = self::points(points, "points")?;
    let slice = pts.as_slice()?;
    let vals = match values {
        None => None,
        Some(v) => {
            let a = crate::convert::real_array(v, "values", "real numbers, one row per point")?;
            let a = if a.getattr("ndim")?.extract::<usize>()? == 1 {
                a.call_method1("reshape", (-1, 1))?
            } else {
                a
            };
            let arr: PyReadonlyArray2<f64> = a
                .extract()
                .map_err(|_| PyValueError::new_err("values must be an (N, C) array"))?;
            Some(arr)
        }
    };
    let stride = vals.as_ref().map_or(0, |v| v.shape()[1]);
    let vslice = vals.as_ref().map(|v| v.as_slice()).transpose()?;
    let (centroids, means) = py
        .detach(|| cloud::voxel_downsample(slice, voxel_size, vslice.map(|v| (v, stride))))
        .py()?;
    let m = centroids.len();
    let means = vals
        .map(|_| numpy::IntoPyArray::into_pyarray(means, py).reshape([m, stride]))
        .transpose()?;
    Ok((rows_to_array(py, centroids)?, means))
}

/// Unit normals (N, 3) facing `viewpoint`, and the surface variation (N,) of each
/// point. Ctrl-C stops it within a fraction of a second (KeyboardInterrupt).
#[pyfunction]
#[pyo3(signature = (points, k=20, viewpoint=None))]
pub fn estimate_normals<'py>(
    py: Python<'py>,
    points: &Bound<'py, PyAny>,
    k: usize,
    viewpoint: Option<&Bound<'py, PyAny>>,
) -> PyResult<VectorsAndValues<'py>> {
    let pts = self::points(points, "points")?;
    let slice = pts.as_slice()?;
    let vp = viewpoint
        .map(|v| vector3(v, "viewpoint"))
        .transpose()?
        .unwrap_or([0.0; 3]);
    let found = detach_interruptible(py, |stop| {
        cloud::estimate_normals_interruptible(slice, k, vp, stop)
    })?;
    let Some((normals, variation)) = found.py()? else {
        // Stopped only when a signal handler raised, which detach_interruptible returned.
        return Err(pyo3::exceptions::PyKeyboardInterrupt::new_err(
            "normal estimation was interrupted",
        ));
    };
    Ok((rows_to_array(py, normals)?, vec_to_array(py, variation)))
}

/// Cluster label (uint32, 0, 1, ... in order of first appearance) per point: points
/// in the same or touching cells of size `cell` (26 neighbours) share a cluster.
#[pyfunction]
#[pyo3(signature = (points, cell))]
pub fn cluster_points<'py>(
    py: Python<'py>,
    points: &Bound<'py, PyAny>,
    cell: f64,
) -> PyResult<Bound<'py, PyArray1<u32>>> {
    let pts = self::points(points, "points")?;
    let slice = pts.as_slice()?;
    let labels = py.detach(|| cloud::cluster_points(slice, cell)).py()?;
    Ok(vec_to_array(py, labels))
}

/// One int64 per point (N, 3) naming its voxel on a grid of edge `resolution`
/// anchored at the origin: cell c = floor(p / resolution) per axis, packed as
/// (cx + 2^20) << 42 | (cy + 2^20) << 21 | (cz + 2^20). For set operations on voxels
/// with numpy (`np.isin`). Points must be finite with |c| < 2^20 on every axis.
#[pyfunction]
#[pyo3(signature = (points, resolution))]
pub fn voxel_codes<'py>(
    py: Python<'py>,
    points: &Bound<'py, PyAny>,
    resolution: f64,
) -> PyResult<Bound<'py, PyArray1<i64>>> {
    let pts = self::points(points, "points")?;
    let slice = pts.as_slice()?;
    let codes = py.detach(|| cloud::voxel_codes(slice, resolution)).py()?;
    Ok(vec_to_array(py, codes))
}

/// Per voxel named by a point in it (`centres` (M, 3), e.g. voxel centres, on the grid
/// of `voxel_codes`), the mean of the `points` (N, 3) in that voxel, or the centre
/// itself where none falls: (M, 3).
#[pyfunction]
#[pyo3(signature = (centres, points, resolution))]
pub fn voxel_means<'py>(
    py: Python<'py>,
    centres: &Bound<'py, PyAny>,
    points: &Bound<'py, PyAny>,
    resolution: f64,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let (c, p) = (
        self::points(centres, "centres")?,
        self::points(points, "points")?,
    );
    let (c, p) = (c.as_slice()?, p.as_slice()?);
    let means = py.detach(|| cloud::voxel_means(c, p, resolution)).py()?;
    rows_to_array(py, means)
}

/// `dst_from_src` (4, 4) minimising Σ wᵢ |R srcᵢ + t − dstᵢ|² (Kabsch), for paired
/// points (N, 3), N ≥ 3 not all on one line.
#[pyfunction]
#[pyo3(signature = (src, dst, weights=None))]
pub fn rigid_fit<'py>(
    py: Python<'py>,
    src: &Bound<'py, PyAny>,
    dst: &Bound<'py, PyAny>,
    weights: Option<&Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let (s, d) = (self::points(src, "src")?, self::points(dst, "dst")?);
    let w = weights.map(|w| numbers(w, "weights")).transpose()?;
    let (s, d) = (s.as_slice()?, d.as_slice()?);
    let m = py.detach(|| cloud::rigid_fit(s, d, w.as_deref())).py()?;
    Ok(matrix4_to_array(py, &m))
}

/// `matrix` as a float64 (4, 4) array after checking it is a finite rigid transform
/// (orthonormal rotation, det +1, bottom row 0 0 0 1); errors name it `name`.
#[pyfunction]
pub fn checked_rigid_transform<'py>(
    py: Python<'py>,
    matrix: &Bound<'py, PyAny>,
    name: &str,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let m = pose(matrix, name)?;
    earcore_core::geometry::check_rigid(&m, name).py()?;
    Ok(matrix4_to_array(py, &m))
}

/// RANSAC rigid fit: (`dst_from_src` (4, 4), inlier mask (N,) bool, inlier RMSE m).
#[pyfunction]
#[pyo3(signature = (src, dst, threshold, iterations=200, seed=0))]
pub fn rigid_fit_ransac<'py>(
    py: Python<'py>,
    src: &Bound<'py, PyAny>,
    dst: &Bound<'py, PyAny>,
    threshold: f64,
    iterations: usize,
    seed: u64,
) -> PyResult<TransformInliersRmse<'py>> {
    let (s, d) = (self::points(src, "src")?, self::points(dst, "dst")?);
    let (s, d) = (s.as_slice()?, d.as_slice()?);
    let found = detach_interruptible(py, |stop| {
        cloud::rigid_fit_ransac_interruptible(s, d, threshold, iterations, seed, stop)
    })?;
    let Some(fit) = found.py()? else {
        // Stopped only when a signal handler raised, which detach_interruptible returned.
        return Err(pyo3::exceptions::PyKeyboardInterrupt::new_err(
            "RANSAC was interrupted",
        ));
    };
    Ok((
        matrix4_to_array(py, &fit.transform),
        vec_to_array(py, fit.inliers),
        fit.rmse,
    ))
}

fn matrix4_to_array<'py>(
    py: Python<'py>,
    m: &earcore_core::na::Matrix4<f64>,
) -> Bound<'py, PyArray2<f64>> {
    numpy::IntoPyArray::into_pyarray(
        numpy::ndarray::Array2::from_shape_fn((4, 4), |(r, c)| m[(r, c)]),
        py,
    )
}

/// Cosine of the angle between each pixel's ray and the surface normal from the depth
/// image's gradients (H, W), NaN where undefined.
#[pyfunction]
pub fn incidence_cosines<'py>(
    py: Python<'py>,
    depth: PyReadonlyArray2<'py, f64>,
    fx: f64,
    fy: f64,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let (h, w) = (depth.shape()[0], depth.shape()[1]);
    let values = crate::convert::contiguous_slice(&depth, "depth")?;
    let out = py
        .detach(|| cloud::incidence_cosines(values, w, h, fx, fy))
        .py()?;
    let image = crate::convert::shaped(numpy::ndarray::Array2::from_shape_vec((h, w), out))?;
    Ok(numpy::IntoPyArray::into_pyarray(image, py))
}
