//! The one table from core errors to Python exceptions.

use earcore_core::geometry::{fmt_num, fmt_point};
use earcore_core::Error;
use pyo3::create_exception;
use pyo3::exceptions::{PyException, PyOSError, PyValueError};
use pyo3::PyErr;

create_exception!(
    earcore,
    EarcoreError,
    PyException,
    "Base class of earcore's own errors."
);
create_exception!(
    earcore,
    OutOfMapError,
    EarcoreError,
    "A coordinate lies outside the area the map can address."
);
create_exception!(
    earcore,
    MapFormatError,
    EarcoreError,
    "A map file or byte stream is corrupt or unsupported."
);

pub fn to_py(e: Error) -> PyErr {
    match e {
        Error::InvalidArgument(msg) => PyValueError::new_err(msg),
        // Numbers as %.6g: a limit at an extreme resolution, or a point at 1e300,
        // would otherwise print hundreds of digits.
        Error::OutOfBounds { what, point, limit } => OutOfMapError::new_err(format!(
            "{what} {} lies outside the map (coordinates must stay within ±{} m at this resolution)",
            fmt_point(&point),
            fmt_num(limit)
        )),
        e @ Error::Format(_) => MapFormatError::new_err(e.to_string()),
        Error::Io(msg) => PyOSError::new_err(msg),
    }
}

/// `?`-friendly conversion for core results.
pub trait IntoPyResult<T> {
    fn py(self) -> pyo3::PyResult<T>;
}

impl<T> IntoPyResult<T> for Result<T, Error> {
    fn py(self) -> pyo3::PyResult<T> {
        self.map_err(to_py)
    }
}
