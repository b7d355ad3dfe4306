//! earcore's core: the numeric work of an environment-aware robot arm, in pure Rust.
//!
//! No Python here: the `earcore-py` crate wraps this one for `import earcore`.
//! nalgebra comes through parry (`earcore_core::na`) so the two never disagree.
//!
//! Each public module is an area. [`octree`] (the occupancy map and the surface map),
//! [`cloud`] (point clouds and ICP) and [`robot`] (kinematics, bodies, collision and
//! clearance) keep their files private and re-export their items at the area's root
//! (`earcore_core::cloud::icp_point_to_plane`); [`geometry`], [`synthetic`] (scenes
//! and sensors for tests and benchmarks), [`threads`], [`eigen3`] and [`floor`] are
//! single files. The most used types are also re-exported here.
//!
//! Units are metres and radians throughout; points are `[f64; 3]` in the map frame
//! unless a function says otherwise.

#![warn(missing_docs)]

pub mod cloud;
pub mod eigen3;
mod error;
pub mod floor;
pub mod geometry;
pub mod octree;
pub mod render;
pub mod robot;
pub mod synthetic;
pub mod threads;

pub use error::{Error, Result};
pub use octree::{DangerParams, DecayMode, OcTree, OcTreeKey, OccupancyParams};
pub use parry3d_f64::na;
