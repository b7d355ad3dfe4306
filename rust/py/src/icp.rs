//! Point-to-plane ICP: `PlaneTarget` (points + normals + index, built once) and the solver.

use earcore_core::cloud::{
    icp_point_to_plane_interruptible, IcpParams, IcpResult, Kernel, PlaneTarget,
    ADAPTIVE_HUBER_SIGMAS,
};
use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray2};
use pyo3::prelude::*;

use crate::convert::{points, pose};
use crate::errors::IntoPyResult;
use crate::interrupt::detach_interruptible;
use crate::surface::PySurfaceMap;

/// Target of point-to-plane ICP: points (N, 3) with normals (N, 3) and a neighbour
/// index, built once and reused by every alignment against it.
#[pyclass(name = "PlaneTarget", module = "earcore", frozen)]
pub struct PyPlaneTarget {
    inner: PlaneTarget,
}

#[pymethods]
impl PyPlaneTarget {
    #[new]
    fn new(
        py: Python<'_>,
        points: &Bound<'_, PyAny>,
        normals: &Bound<'_, PyAny>,
    ) -> PyResult<Self> {
        let p = self::points(points, "points")?;
        let n = self::points(normals, "normals")?;
        let (p, n) = (p.as_slice()?, n.as_slice()?);
        Ok(PyPlaneTarget {
            inner: py.detach(|| PlaneTarget::new(p, n)).py()?,
        })
    }

    fn __len__(&self) -> usize {
        self.inner.len()
    }
}

/// Outcome of an alignment.
#[pyclass(name = "IcpResult", module = "earcore", frozen, get_all)]
pub struct PyIcpResult {
    /// `target_from_source` (4, 4).
    transform: Py<PyArray2<f64>>,
    /// RMS point-to-plane distance of the pairs at the end (metres).
    rmse: f64,
    /// Fraction of source points paired within the correspondence distance.
    fitness: f64,
    iterations: usize,
    converged: bool,
    /// The geometry cannot fix all six degrees of freedom (e.g. one plane).
    degenerate: bool,
    /// Smallest / largest eigenvalue of the scale-balanced normal equations.
    conditioning: f64,
}

#[pymethods]
impl PyIcpResult {
    fn __repr__(&self) -> String {
        format!(
            "IcpResult(rmse={:.6}, fitness={:.3}, iterations={}, converged={}, degenerate={})",
            self.rmse, self.fitness, self.iterations, self.converged, self.degenerate
        )
    }
}

fn to_py(py: Python<'_>, r: IcpResult) -> PyResult<PyIcpResult> {
    let m = Array2::from_shape_fn((4, 4), |(i, j)| r.transform[(i, j)]);
    Ok(PyIcpResult {
        transform: m.into_pyarray(py).unbind(),
        rmse: r.rmse,
        fitness: r.fitness,
        iterations: r.iterations,
        converged: r.converged,
        degenerate: r.degenerate,
        conditioning: r.conditioning,
    })
}

/// Align `source` (N, 3) to a `PlaneTarget` or a `SurfaceMap` from `initial` (4, 4;
/// identity if None). Ctrl-C stops it between iterations (KeyboardInterrupt).
#[pyfunction]
#[pyo3(signature = (source, target, initial=None, *, max_iterations=50, max_correspondence_distance=0.2,
                    translation_tolerance=0.0, rotation_tolerance=0.0, sigma_tolerance=1.0, huber_delta=None, adaptive_huber=false))]
#[allow(clippy::too_many_arguments)]
pub fn icp_point_to_plane_raw(
    py: Python<'_>,
    source: &Bound<'_, PyAny>,
    target: &Bound<'_, PyAny>,
    initial: Option<&Bound<'_, PyAny>>,
    max_iterations: usize,
    max_correspondence_distance: f64,
    translation_tolerance: f64,
    rotation_tolerance: f64,
    sigma_tolerance: f64,
    huber_delta: Option<f64>,
    adaptive_huber: bool,
) -> PyResult<PyIcpResult> {
    let src = points(source, "source")?;
    let src = src.as_slice()?;
    let initial = match initial {
        Some(m) => pose(m, "initial")?,
        None => earcore_core::na::Matrix4::identity(),
    };
    let params = IcpParams {
        max_iterations,
        max_correspondence_distance,
        translation_tolerance,
        rotation_tolerance,
        sigma_tolerance,
        kernel: match (huber_delta, adaptive_huber) {
            (Some(_), true) => {
                return Err(pyo3::exceptions::PyValueError::new_err(
                    "give huber_delta (a fixed width) or adaptive_huber, not both",
                ))
            }
            (Some(delta), false) => Kernel::Huber(delta),
            (None, true) => Kernel::AdaptiveHuber(ADAPTIVE_HUBER_SIGMAS),
            (None, false) => Kernel::Squared,
        },
    };
    let result = if let Ok(t) = target.cast::<PyPlaneTarget>() {
        let t = t.get();
        detach_interruptible(py, |stop| {
            icp_point_to_plane_interruptible(src, &t.inner, &initial, params, stop)
        })?
    } else if let Ok(m) = target.cast::<PySurfaceMap>() {
        let m = m.get();
        detach_interruptible(py, |stop| {
            icp_point_to_plane_interruptible(src, &*m.hold(), &initial, params, stop)
        })?
    } else {
        return Err(pyo3::exceptions::PyTypeError::new_err(
            "target must be a PlaneTarget or a SurfaceMap",
        ));
    };
    match result.py()? {
        Some(r) => to_py(py, r),
        // Stopped only when a signal handler raised, which detach_interruptible returned.
        None => Err(pyo3::exceptions::PyKeyboardInterrupt::new_err(
            "ICP was interrupted",
        )),
    }
}
