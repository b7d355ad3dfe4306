//! earcore's core: the numeric work of an environment-aware robot arm, in pure Rust.
//!
//! No Python here: the `earcore-py` crate wraps this one for `import earcore`.
//! nalgebra comes through parry (`earcore_core::na`) so the two never disagree.

pub mod cloud;
pub mod eigen3;
pub mod error;
pub mod floor;
pub mod geometry;
pub mod octree;
pub mod robot;
pub mod synthetic;
pub mod threads;

pub use error::{Error, Result};
pub use octree::{DangerParams, DecayMode, OcTree, OcTreeKey, OccupancyParams};
pub use parry3d_f64::na;
