//! The core's one error type; the binding maps each variant to a Python exception.

use thiserror::Error;

#[derive(Debug, Error, Clone, PartialEq)]
pub enum Error {
    /// An argument is outside its domain (non-finite, non-positive, wrong length...).
    #[error("{0}")]
    InvalidArgument(String),
    /// A coordinate cannot be addressed by the tree's 16-bit keys at this resolution.
    #[error("{what} {point:?} lies outside the map (coordinates must stay within ±{limit} m at this resolution)")]
    OutOfBounds {
        what: &'static str,
        point: [f64; 3],
        limit: f64,
    },
    /// A file or byte stream is not a valid OctoMap tree.
    #[error("corrupt or unsupported OctoMap data: {0}")]
    Format(String),
    #[error("I/O error: {0}")]
    Io(String),
}

impl From<std::io::Error> for Error {
    fn from(e: std::io::Error) -> Self {
        Error::Io(e.to_string())
    }
}

pub type Result<T> = std::result::Result<T, Error>;
