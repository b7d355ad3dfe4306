//! Synthetic depth frames (analytic scenes) for tests, benchmarks and demos.

use earcore_core::na::Matrix4;
use earcore_core::synthetic::{
    benchmark_scene, lidar_scan, render_points, Lidar, PinholeCamera, Shape,
};
use numpy::{PyArray1, PyArray2, PyReadonlyArray2};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::convert::{rows_to_array, vec_to_array};

/// Most rays one synthetic frame may cast (a 4096 × 4096 image): sizes come from the
/// caller, and the points are allocated before anything is cast.
const MAX_RAYS: usize = 1 << 24;

/// A finite (4, 4) pose in any numeric dtype (the shared converter, plus finiteness).
fn pose_from(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<Matrix4<f64>> {
    let m = crate::convert::pose(obj, name)?;
    if !m.iter().all(|v| v.is_finite()) {
        return Err(PyValueError::new_err(format!(
            "{name} must be a finite (4, 4) matrix"
        )));
    }
    Ok(m)
}

/// Spheres (K, 4: centre, radius), axis-aligned boxes (K, 6: lo, hi) and an optional
/// floor at z = `floor_z` as core shapes.
fn shapes_from<'py>(
    py: Python<'py>,
    spheres: &Bound<'py, PyAny>,
    boxes: &Bound<'py, PyAny>,
    floor_z: Option<f64>,
) -> PyResult<Vec<Shape>> {
    let mut shapes: Vec<Shape> = floor_z.map(|z| Shape::Floor { z }).into_iter().collect();
    let np = PyModule::import(py, "numpy")?;
    // A table of K rows of n finite numbers (one row may come flat; empty is none).
    let rows = |obj: &Bound<'py, PyAny>, n: usize, name: &str| -> PyResult<Vec<Vec<f64>>> {
        let bad =
            || PyValueError::new_err(format!("{name} must be a (K, {n}) array of finite numbers"));
        let a = np
            .call_method1("asarray", (obj, np.getattr("float64")?))
            .map_err(|_| bad())?;
        let shape: Vec<usize> = a.getattr("shape")?.extract()?;
        let a = match shape.as_slice() {
            [0] | [0, _] => return Ok(Vec::new()),
            [k] if *k == n => a.call_method1("reshape", (1, n))?,
            [_, k] if *k == n => a,
            _ => return Err(bad()),
        };
        let a: PyReadonlyArray2<f64> = a.extract().map_err(|_| bad())?;
        let table: Vec<Vec<f64>> = a
            .as_array()
            .rows()
            .into_iter()
            .map(|r| r.to_vec())
            .collect();
        if !table.iter().flatten().all(|v| v.is_finite()) {
            return Err(bad());
        }
        Ok(table)
    };
    for s in rows(spheres, 4, "spheres")? {
        if s[3] <= 0.0 {
            return Err(PyValueError::new_err(format!(
                "a sphere's radius must be > 0, got {}",
                s[3]
            )));
        }
        shapes.push(Shape::Sphere {
            center: [s[0], s[1], s[2]],
            radius: s[3],
        });
    }
    for b in rows(boxes, 6, "boxes")? {
        if !(b[0] <= b[3] && b[1] <= b[4] && b[2] <= b[5]) {
            return Err(PyValueError::new_err(format!(
                "a box needs lo <= hi on every axis, got {b:?}"
            )));
        }
        shapes.push(Shape::Box {
            lo: [b[0], b[1], b[2]],
            hi: [b[3], b[4], b[5]],
        });
    }
    Ok(shapes)
}

/// One turn of a multi-line lidar (VLP-16-like by default) at `base_from_sensor` in a
/// scene of spheres, boxes (a box around the sensor is the room) and an optional
/// floor: points (N, 3) in the sensor frame, ring by ring, with Gaussian range noise
/// reproducible from `seed`.
#[pyfunction]
#[pyo3(signature = (base_from_sensor, spheres, boxes, floor_z=None, *, rings=16, azimuth_steps=940,
                    vertical_fov_deg=30.0, max_range=100.0, noise_sigma=0.015, seed=0))]
#[allow(clippy::too_many_arguments)]
pub fn render_lidar_scan<'py>(
    py: Python<'py>,
    base_from_sensor: &Bound<'py, PyAny>,
    spheres: &Bound<'py, PyAny>,
    boxes: &Bound<'py, PyAny>,
    floor_z: Option<f64>,
    rings: usize,
    azimuth_steps: usize,
    vertical_fov_deg: f64,
    max_range: f64,
    noise_sigma: f64,
    seed: u64,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let pose = pose_from(base_from_sensor, "base_from_sensor")?;
    if rings == 0
        || azimuth_steps == 0
        || !(max_range > 0.0 && noise_sigma >= 0.0 && vertical_fov_deg.is_finite())
        || !(max_range.is_finite() && noise_sigma.is_finite())
    {
        return Err(PyValueError::new_err(format!(
            "lidar needs rings and azimuth_steps > 0, a finite max_range > 0, a finite \
             noise_sigma >= 0 and a finite vertical_fov_deg; got rings={rings}, \
             azimuth_steps={azimuth_steps}, max_range={max_range}, noise_sigma={noise_sigma}, \
             vertical_fov_deg={vertical_fov_deg}"
        )));
    }
    if rings.saturating_mul(azimuth_steps) > MAX_RAYS {
        return Err(PyValueError::new_err(format!(
            "rings × azimuth_steps = {rings} × {azimuth_steps} is more than {MAX_RAYS} beams"
        )));
    }
    let lidar = Lidar {
        rings,
        azimuth_steps,
        vertical_fov: vertical_fov_deg.to_radians(),
        max_range,
        noise_sigma,
    };
    let shapes = shapes_from(py, spheres, boxes, floor_z)?;
    let pts = py.detach(|| lidar_scan(&lidar, &pose, &shapes, seed));
    rows_to_array(py, pts)
}

/// Render the points a pinhole depth camera sees of spheres (K, 4: centre, radius),
/// axis-aligned boxes (K, 6: lo, hi) and an optional floor at z = `floor_z`.
#[pyfunction]
#[pyo3(signature = (base_from_camera, spheres, boxes, floor_z=None, *, width=512, height=424, fx=365.0, fy=365.0, cx=256.0, cy=212.0, max_depth=4.5))]
#[allow(clippy::too_many_arguments)]
pub fn render_depth_points<'py>(
    py: Python<'py>,
    base_from_camera: &Bound<'py, PyAny>,
    spheres: &Bound<'py, PyAny>,
    boxes: &Bound<'py, PyAny>,
    floor_z: Option<f64>,
    width: usize,
    height: usize,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    max_depth: f64,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let pose = pose_from(base_from_camera, "base_from_camera")?;
    let camera = PinholeCamera {
        width,
        height,
        fx,
        fy,
        cx,
        cy,
        max_depth,
    };
    let finite = [fx, fy, cx, cy, max_depth].iter().all(|v| v.is_finite());
    if width == 0 || height == 0 || !(finite && fx > 0.0 && fy > 0.0 && max_depth > 0.0) {
        return Err(PyValueError::new_err(format!(
            "camera needs width and height > 0, finite fx, fy, max_depth > 0 and finite cx, cy; \
             got width={width}, height={height}, fx={fx}, fy={fy}, cx={cx}, cy={cy}, \
             max_depth={max_depth}"
        )));
    }
    if width.saturating_mul(height) > MAX_RAYS {
        return Err(PyValueError::new_err(format!(
            "width × height = {width} × {height} is more than {MAX_RAYS} pixels"
        )));
    }
    let shapes = shapes_from(py, spheres, boxes, floor_z)?;
    let pts = py.detach(|| render_points(&camera, &pose, &shapes));
    rows_to_array(py, pts)
}

/// Points (N, 3) and the sensor origin (3,).
type Scan<'py> = (Bound<'py, PyArray2<f64>>, Bound<'py, PyArray1<f64>>);

/// The scene all benchmarks share: returns (points (N, 3), sensor origin (3,)).
#[pyfunction]
pub fn benchmark_frame(py: Python<'_>) -> PyResult<Scan<'_>> {
    let (camera, pose, shapes) = benchmark_scene();
    let pts = py.detach(|| render_points(&camera, &pose, &shapes));
    let origin = vec![pose[(0, 3)], pose[(1, 3)], pose[(2, 3)]];
    Ok((rows_to_array(py, pts)?, vec_to_array(py, origin)))
}

/// Occupied cell centres (N, 3) of the robot work cell the collision benchmarks share
/// (about 20k cells at 5 cm); feed them to `OcTree.update_nodes`.
#[pyfunction]
#[pyo3(signature = (resolution = 0.05, seed = 0))]
pub fn robot_cell_voxels(
    py: Python<'_>,
    resolution: f64,
    seed: u64,
) -> PyResult<Bound<'_, PyArray2<f64>>> {
    if !(resolution.is_finite() && resolution >= 0.005) {
        return Err(PyValueError::new_err(format!(
            "resolution must be at least 0.005 m, got {resolution}"
        )));
    }
    let cells = py.detach(|| earcore_core::synthetic::robot_cell_voxels(resolution, seed));
    rows_to_array(py, cells)
}
