//! `earcore._earcore.Follower`: the trajectory follower's control law and roll-out
//! (`earcore_core::robot::follower`), wrapped by `earcore.planning.follower`.
//!
//! Called every control step and inside reflexes, so the limits are converted once (in
//! the constructor) and float64 vectors are read without a numpy call.

use earcore_core::robot::follower;
use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray1, PyArray2, PyArrayMethods};
use pyo3::prelude::*;

use crate::convert::{configurations, numbers};
use crate::errors::IntoPyResult;

/// A float64 vector: borrowed straight from a contiguous float64 array, else via numpy.
fn vector(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<Vec<f64>> {
    if let Ok(array) = obj.cast::<PyArray1<f64>>() {
        if let Ok(view) = array.try_readonly() {
            if let Ok(values) = view.as_slice() {
                return Ok(values.to_vec());
            }
        }
    }
    numbers(obj, name)
}

#[pyclass(name = "Follower", module = "earcore._earcore", frozen)]
pub struct PyFollower {
    inner: follower::Follower,
}

/// (states (n, dof), rejoined, steps, largest error).
type RolloutTuple<'py> = (Bound<'py, PyArray2<f64>>, bool, usize, f64);

#[pymethods]
impl PyFollower {
    #[new]
    #[pyo3(signature = (max_velocity, max_acceleration, gain))]
    fn new(
        max_velocity: &Bound<'_, PyAny>,
        max_acceleration: &Bound<'_, PyAny>,
        gain: f64,
    ) -> PyResult<Self> {
        let v = numbers(max_velocity, "max_velocity")?;
        let a = numbers(max_acceleration, "max_acceleration")?;
        Ok(Self {
            inner: follower::Follower::new(v, a, gain).py()?,
        })
    }

    /// The next velocity command (dof,) from position `q` and the `last` command,
    /// tracking the reference at `now` and one step `ahead` (both None: stop).
    #[pyo3(signature = (q, last, now, ahead, dt))]
    fn command<'py>(
        &self,
        py: Python<'py>,
        q: &Bound<'py, PyAny>,
        last: &Bound<'py, PyAny>,
        now: Option<&Bound<'py, PyAny>>,
        ahead: Option<&Bound<'py, PyAny>>,
        dt: f64,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let (q, last) = (vector(q, "q")?, vector(last, "last")?);
        let reference = match (now, ahead) {
            (Some(now), Some(ahead)) => Some((vector(now, "now")?, vector(ahead, "ahead")?)),
            (None, None) => None,
            _ => {
                return Err(pyo3::exceptions::PyValueError::new_err(
                    "give both `now` and `ahead`, or neither (stop)",
                ))
            }
        };
        let reference = reference
            .as_ref()
            .map(|(n, a)| (n.as_slice(), a.as_slice()));
        let out = self.inner.command(&q, &last, reference, dt).py()?;
        Ok(out.into_pyarray(py))
    }

    /// Follow `reference` (K, dof), one row per step, K ≥ 3, from `q` moving at
    /// `command`, the joints clamped to [`lower`, `upper`]: (states, rejoined, steps,
    /// largest error); see `earcore_core::robot::follower::Follower::rollout`.
    #[allow(clippy::too_many_arguments)]
    #[pyo3(signature = (reference, q, command, dt, lower, upper, tolerance))]
    fn rollout<'py>(
        &self,
        py: Python<'py>,
        reference: &Bound<'py, PyAny>,
        q: &Bound<'py, PyAny>,
        command: &Bound<'py, PyAny>,
        dt: f64,
        lower: &Bound<'py, PyAny>,
        upper: &Bound<'py, PyAny>,
        tolerance: f64,
    ) -> PyResult<RolloutTuple<'py>> {
        let dof = self.inner.dof();
        let (reference, _, _) = configurations(reference, dof, "reference")?;
        let (q, command) = (vector(q, "q")?, vector(command, "command")?);
        let (lower, upper) = (vector(lower, "lower")?, vector(upper, "upper")?);
        let r = self
            .inner
            .rollout(&reference, &q, &command, dt, &lower, &upper, tolerance)
            .py()?;
        let rows = r.states.len() / dof;
        let states = Array2::from_shape_vec((rows, dof), r.states)
            .map_err(|e| pyo3::exceptions::PyValueError::new_err(e.to_string()))?;
        Ok((
            states.into_pyarray(py),
            r.rejoined,
            r.steps,
            r.largest_error,
        ))
    }
}
