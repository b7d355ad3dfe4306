//! The only numpy ⇄ Rust conversions: inputs are normalised once (dtype float64,
//! C-contiguous, checked shape) and borrowed without copying; outputs are handed to
//! numpy without copying.

use numpy::ndarray::Array2;
use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2,
    PyUntypedArrayMethods,
};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyModule;

/// An (N, 3) float64 array held for reading.
pub struct Points<'py>(PyReadonlyArray2<'py, f64>);

impl Points<'_> {
    pub fn as_slice(&self) -> PyResult<&[[f64; 3]]> {
        // Made C-contiguous in `points`; (N, 3) contiguous float64 is N consecutive [f64; 3].
        let flat = self
            .0
            .as_slice()
            .map_err(|e| PyValueError::new_err(format!("points are not contiguous: {e}")))?;
        let (chunks, rest) = flat.as_chunks::<3>();
        debug_assert!(rest.is_empty());
        Ok(chunks)
    }
}

fn as_contiguous_f64<'py>(obj: &Bound<'py, PyAny>) -> PyResult<Bound<'py, PyAny>> {
    let np = PyModule::import(obj.py(), "numpy")?;
    np.call_method1("ascontiguousarray", (obj, np.getattr("float64")?))
}

/// Accept anything numpy can read as (N, 3) numbers.
pub fn points<'py>(obj: &Bound<'py, PyAny>, name: &str) -> PyResult<Points<'py>> {
    let arr = match obj.cast::<PyArray2<f64>>() {
        Ok(a) if a.is_c_contiguous() => a.readonly(),
        _ => {
            let converted = as_contiguous_f64(obj).map_err(|e| {
                pyo3::exceptions::PyTypeError::new_err(format!(
                    "{name} must be an (N, 3) array of numbers: {e}"
                ))
            })?;
            match converted.cast::<PyArray2<f64>>() {
                Ok(a) => a.readonly(),
                Err(_) => {
                    let shape: Vec<usize> = converted
                        .cast::<numpy::PyUntypedArray>()
                        .map(|a| a.shape().to_vec())
                        .unwrap_or_default();
                    return Err(PyValueError::new_err(format!(
                        "{name} must be an (N, 3) array, got shape {shape:?} (use .reshape(-1, 3) for one point)"
                    )));
                }
            }
        }
    };
    if arr.shape()[1] != 3 {
        return Err(PyValueError::new_err(format!(
            "{name} must be an (N, 3) array, got shape {:?}",
            arr.shape()
        )));
    }
    Ok(Points(arr))
}

/// One 3-vector (a point or a direction).
pub fn vector3(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<[f64; 3]> {
    let converted = as_contiguous_f64(obj).map_err(|e| {
        pyo3::exceptions::PyTypeError::new_err(format!("{name} must be 3 numbers: {e}"))
    })?;
    let arr: PyReadonlyArray1<f64> = converted
        .extract()
        .map_err(|_| PyValueError::new_err(format!("{name} must be 3 numbers (x, y, z)")))?;
    match arr.as_slice() {
        Ok(&[x, y, z]) => Ok([x, y, z]),
        _ => Err(PyValueError::new_err(format!(
            "{name} must be 3 numbers (x, y, z), got {} values",
            arr.len()
        ))),
    }
}

/// Rows of three into an (M, 3) float64 array, without copying.
pub fn rows_to_array<'py>(
    py: Python<'py>,
    rows: Vec<[f64; 3]>,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let m = rows.len();
    let flat: Vec<f64> = rows.into_flattened();
    let array =
        Array2::from_shape_vec((m, 3), flat).map_err(|e| PyValueError::new_err(e.to_string()))?;
    Ok(array.into_pyarray(py))
}

/// Columns of `R` numbers into an (R, K) float64 array (e.g. a Jacobian, one column
/// per joint).
pub fn columns_to_array<'py, const R: usize>(
    py: Python<'py>,
    columns: &[[f64; R]],
) -> Bound<'py, PyArray2<f64>> {
    Array2::from_shape_fn((R, columns.len()), |(r, c)| columns[c][r]).into_pyarray(py)
}

pub fn vec_to_array<'py, T: numpy::Element>(py: Python<'py>, v: Vec<T>) -> Bound<'py, PyArray1<T>> {
    v.into_pyarray(py)
}

/// A (4, 4) float64 rigid transform (checked by the core where it is used).
pub fn pose(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<earcore_core::na::Matrix4<f64>> {
    let converted = as_contiguous_f64(obj).map_err(|e| {
        pyo3::exceptions::PyTypeError::new_err(format!("{name} must be a (4, 4) matrix: {e}"))
    })?;
    let arr: PyReadonlyArray2<f64> = converted
        .extract()
        .map_err(|_| PyValueError::new_err(format!("{name} must be a (4, 4) matrix")))?;
    let a = arr.as_array();
    if a.shape() != [4, 4] {
        return Err(PyValueError::new_err(format!(
            "{name} must be a (4, 4) matrix, got shape {:?}",
            a.shape()
        )));
    }
    Ok(earcore_core::na::Matrix4::from_fn(|r, c| a[[r, c]]))
}

/// Numbers as a flat float64 vector (e.g. distortion coefficients).
pub fn numbers(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<Vec<f64>> {
    let np = PyModule::import(obj.py(), "numpy")?;
    let a = np
        .call_method1("ascontiguousarray", (obj, np.getattr("float64")?))
        .and_then(|a| a.call_method1("ravel", ()))
        .map_err(|e| {
            pyo3::exceptions::PyTypeError::new_err(format!("{name} must be numbers: {e}"))
        })?;
    let arr: PyReadonlyArray1<f64> = a.extract()?;
    Ok(arr.as_slice()?.to_vec())
}

/// Joint configurations: (dof,) or (K, dof) numbers → (row-major values, K, whether
/// a single configuration was given).
pub fn configurations(
    obj: &Bound<'_, PyAny>,
    dof: usize,
    name: &str,
) -> PyResult<(Vec<f64>, usize, bool)> {
    let converted = as_contiguous_f64(obj).map_err(|e| {
        pyo3::exceptions::PyTypeError::new_err(format!("{name} must be joint values: {e}"))
    })?;
    let arr = converted
        .cast::<numpy::PyUntypedArray>()
        .map_err(|_| PyValueError::new_err(format!("{name} must be an array of joint values")))?;
    let shape = arr.shape().to_vec();
    let (k, single) = match shape.as_slice() {
        [n] if *n == dof => (1, true),
        [k, n] if *n == dof => (*k, false),
        _ => {
            return Err(PyValueError::new_err(format!(
                "{name} must have shape ({dof},) or (K, {dof}) for this robot, got {shape:?}"
            )))
        }
    };
    let flat = converted.call_method1("ravel", ())?;
    let values: PyReadonlyArray1<f64> = flat.extract()?;
    Ok((values.as_slice()?.to_vec(), k, single))
}
