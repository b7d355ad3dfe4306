//! The core's one error type; the binding maps each variant to a Python exception.

use thiserror::Error;

/// The core's error: every fallible function returns it through [`Result`].
#[derive(Debug, Error, Clone, PartialEq)]
pub enum Error {
    /// An argument is outside its domain (non-finite, non-positive, wrong length...).
    #[error("{0}")]
    InvalidArgument(String),
    /// A coordinate cannot be addressed by the tree's 16-bit keys at this resolution.
    #[error("{what} {point:?} lies outside the map (coordinates must stay within ±{limit} m at this resolution)")]
    OutOfBounds {
        /// What was being addressed (e.g. "point", "origin").
        what: &'static str,
        /// The offending coordinates, in metres.
        point: [f64; 3],
        /// The largest coordinate magnitude the map can address, in metres.
        limit: f64,
    },
    /// A file or byte stream is not a valid OctoMap tree.
    #[error("corrupt or unsupported OctoMap data: {0}")]
    Format(String),
    /// Reading or writing a file failed (the operating system's message).
    #[error("I/O error: {0}")]
    Io(String),
}

impl From<std::io::Error> for Error {
    fn from(e: std::io::Error) -> Self {
        Error::Io(e.to_string())
    }
}

/// `std::result::Result` with the core's [`Error`](enum@Error).
pub type Result<T> = std::result::Result<T, Error>;
