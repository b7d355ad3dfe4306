//! The only numpy ⇄ Rust conversions: inputs are normalised once (dtype float64,
//! C-contiguous and aligned, checked shape) and borrowed without copying when they
//! already are; outputs are handed to numpy without copying.
//!
//! Only real numbers pass: masked arrays (whose data would be read with the mask
//! ignored), complex arrays (whose imaginary part would be dropped), object, string,
//! boolean and date arrays raise `TypeError` naming the parameter.

use numpy::ndarray::Array2;
use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyArrayDescrMethods, PyArrayMethods, PyReadonlyArray1,
    PyReadonlyArray2, PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyModule;

/// An (N, 3) float64 array held for reading.
pub struct Points<'py>(PyReadonlyArray2<'py, f64>);

impl Points<'_> {
    pub fn as_slice(&self) -> PyResult<&[[f64; 3]]> {
        // Made C-contiguous and aligned in `points`; (N, 3) contiguous float64 is N
        // consecutive [f64; 3].
        let flat = self.0.as_slice().map_err(|_| {
            PyValueError::new_err("points must be a C-contiguous, aligned float64 array")
        })?;
        let (chunks, rest) = flat.as_chunks::<3>();
        debug_assert!(rest.is_empty());
        Ok(chunks)
    }
}

/// `obj` as a C-contiguous, aligned float64 ndarray (the same object when it already
/// is one), or a `TypeError` naming `name` and `what` it must be. numpy's
/// `ascontiguousarray` keeps misaligned arrays as they are and reads masked arrays'
/// data without their masks, so both are handled here first.
pub fn real_array<'py>(
    obj: &Bound<'py, PyAny>,
    name: &str,
    what: &str,
) -> PyResult<Bound<'py, PyAny>> {
    // The common case, already a plain ndarray as needed (exactly ndarray: subclasses
    // such as masked arrays take the checked path), costs no numpy call.
    if is_plain_f64(obj) {
        return Ok(obj.clone());
    }
    let py = obj.py();
    let np = PyModule::import(py, "numpy")?;
    // Only ndarray subclasses can be masked arrays (lists skip the look-up).
    let is_array = obj.cast::<numpy::PyUntypedArray>().is_ok();
    if is_array && !obj.is_exact_instance_of::<numpy::PyUntypedArray>() {
        let ma = np.getattr("ma")?.getattr("MaskedArray")?;
        if obj.is_instance(&ma)? {
            return Err(PyTypeError::new_err(format!(
                "{name} is a masked array: pass plain numbers (e.g. drop the masked rows, or \
                 .filled(np.nan) where NaN is accepted), since the mask cannot be honoured"
            )));
        }
    }
    let arr = np.call_method1("asarray", (obj,)).map_err(|e| {
        PyTypeError::new_err(format!("{name} must be {what}: {}", short(&e.to_string())))
    })?;
    let kind = arr
        .cast::<numpy::PyUntypedArray>()
        .map(|a| a.dtype().kind())
        .unwrap_or(b'O');
    let why = match kind {
        b'f' | b'i' | b'u' => None,
        b'c' => Some("complex numbers (the imaginary part would be lost)"),
        b'b' => Some("booleans"),
        b'O' => Some("Python objects (dtype=object)"),
        b'U' | b'S' => Some("strings"),
        b'M' | b'm' => Some("dates or durations"),
        _ => Some("not numbers"),
    };
    if let Some(why) = why {
        return Err(PyTypeError::new_err(format!(
            "{name} must be {what} (real numbers), got {why}"
        )));
    }
    if is_plain_f64(&arr) {
        return Ok(arr);
    }
    let arr = np
        .call_method1("ascontiguousarray", (arr, np.getattr("float64")?))
        .map_err(|e| {
            PyTypeError::new_err(format!("{name} must be {what}: {}", short(&e.to_string())))
        })?;
    if is_plain_f64(&arr) {
        Ok(arr)
    } else {
        // Misaligned data stays misaligned through ascontiguousarray; a copy is
        // aligned (numpy allocates aligned memory).
        arr.call_method0("copy")
    }
}

/// Whether `obj` is exactly an ndarray of float64, C-contiguous and aligned.
fn is_plain_f64(obj: &Bound<'_, PyAny>) -> bool {
    obj.is_exact_instance_of::<numpy::PyUntypedArray>()
        && obj
            .cast::<numpy::PyArrayDyn<f64>>()
            .is_ok_and(|a| a.is_c_contiguous() && a.is_aligned())
}

/// The first line of an error text, at most 200 characters (numpy's messages can
/// repeat a whole input).
fn short(message: &str) -> String {
    let line = message.lines().next().unwrap_or("");
    if line.chars().count() > 200 {
        format!("{}…", line.chars().take(200).collect::<String>())
    } else {
        line.to_owned()
    }
}

/// Accept anything numpy can read as (N, 3) real numbers.
pub fn points<'py>(obj: &Bound<'py, PyAny>, name: &str) -> PyResult<Points<'py>> {
    // The common case, a plain C-contiguous aligned float64 (N, 3) ndarray, is borrowed.
    let fast = obj
        .cast::<PyArray2<f64>>()
        .ok()
        .filter(|_| is_plain_f64(obj));
    let arr = match fast {
        Some(a) => a.readonly(),
        None => {
            let converted = real_array(obj, name, "an (N, 3) array of numbers")?;
            match converted.cast::<PyArray2<f64>>() {
                Ok(a) => a.readonly(),
                Err(_) => {
                    let shape: Vec<usize> = converted
                        .cast::<numpy::PyUntypedArray>()
                        .map(|a| a.shape().to_vec())
                        .unwrap_or_default();
                    return Err(PyValueError::new_err(format!(
                        "{name} must be an (N, 3) array, got shape {} (use .reshape(-1, 3) for one point)",
                        fmt_shape(&shape)
                    )));
                }
            }
        }
    };
    if arr.shape()[1] != 3 {
        return Err(PyValueError::new_err(format!(
            "{name} must be an (N, 3) array, got shape {}",
            fmt_shape(arr.shape())
        )));
    }
    Ok(Points(arr))
}

/// A shape as numpy prints it: `(4, 2)`, `(3,)`, `()`.
pub fn fmt_shape(shape: &[usize]) -> String {
    match shape {
        [n] => format!("({n},)"),
        _ => format!(
            "({})",
            shape
                .iter()
                .map(usize::to_string)
                .collect::<Vec<_>>()
                .join(", ")
        ),
    }
}

/// One 3-vector (a point or a direction).
pub fn vector3(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<[f64; 3]> {
    let converted = real_array(obj, name, "3 numbers (x, y, z)")?;
    let arr: PyReadonlyArray1<f64> = converted.extract().map_err(|_| {
        PyValueError::new_err(format!(
            "{name} must be 3 numbers (x, y, z), got shape {}",
            shape_of(&converted)
        ))
    })?;
    match arr.as_slice() {
        Ok(&[x, y, z]) => Ok([x, y, z]),
        _ => Err(PyValueError::new_err(format!(
            "{name} must be 3 numbers (x, y, z), got {} values",
            arr.len()
        ))),
    }
}

fn shape_of(arr: &Bound<'_, PyAny>) -> String {
    arr.cast::<numpy::PyUntypedArray>()
        .map(|a| fmt_shape(a.shape()))
        .unwrap_or_else(|_| "?".into())
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
    let converted = real_array(obj, name, "a (4, 4) matrix")?;
    let arr: PyReadonlyArray2<f64> = converted.extract().map_err(|_| {
        PyValueError::new_err(format!(
            "{name} must be a (4, 4) matrix, got shape {}",
            shape_of(&converted)
        ))
    })?;
    let a = arr.as_array();
    if a.shape() != [4, 4] {
        return Err(PyValueError::new_err(format!(
            "{name} must be a (4, 4) matrix, got shape {}",
            fmt_shape(a.shape())
        )));
    }
    Ok(earcore_core::na::Matrix4::from_fn(|r, c| a[[r, c]]))
}

/// Numbers as a flat float64 vector (e.g. distortion coefficients).
pub fn numbers(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<Vec<f64>> {
    let flat = real_array(obj, name, "numbers")?.call_method1("ravel", ())?;
    let arr: PyReadonlyArray1<f64> = flat.extract()?;
    Ok(arr.as_array().to_vec())
}

/// Joint configurations: (dof,) or (K, dof) numbers → (row-major values, K, whether
/// a single configuration was given).
pub fn configurations(
    obj: &Bound<'_, PyAny>,
    dof: usize,
    name: &str,
) -> PyResult<(Vec<f64>, usize, bool)> {
    let converted = real_array(obj, name, "joint values")?;
    let arr = converted
        .cast::<numpy::PyUntypedArray>()
        .map_err(|_| PyValueError::new_err(format!("{name} must be an array of joint values")))?;
    let shape = arr.shape().to_vec();
    let (k, single) = match shape.as_slice() {
        [n] if *n == dof => (1, true),
        [k, n] if *n == dof => (*k, false),
        _ => {
            return Err(PyValueError::new_err(format!(
                "{name} must have shape ({dof},) or (K, {dof}) for this robot, got {}",
                fmt_shape(&shape)
            )))
        }
    };
    let flat = converted.call_method1("ravel", ())?;
    let values: PyReadonlyArray1<f64> = flat.extract()?;
    Ok((values.as_array().to_vec(), k, single))
}

/// A C-contiguous array's values, borrowed (the Python layer makes arrays contiguous:
/// copying here could meet a broadcast array of any size).
pub fn contiguous_slice<'a, T: numpy::Element, D: numpy::ndarray::Dimension>(
    array: &'a numpy::PyReadonlyArray<'_, T, D>,
    name: &str,
) -> PyResult<&'a [T]> {
    array.as_slice().map_err(|_| {
        pyo3::exceptions::PyTypeError::new_err(format!("{name} must be a C-contiguous array"))
    })
}

/// A core result's values laid out as an array; the sizes agree by construction, and
/// should they not, a `ValueError` rather than a panic.
pub fn shaped<A>(array: Result<A, numpy::ndarray::ShapeError>) -> PyResult<A> {
    array.map_err(|e| {
        PyValueError::new_err(format!("internal error: a result of the wrong size ({e})"))
    })
}
