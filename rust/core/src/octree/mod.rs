//! The workspace map: an occupancy octree with OctoMap's semantics and file formats,
//! plus per-voxel danger decay.

mod arena;
mod danger;
mod io;
mod key;
mod occupancy;
mod ray;
mod scan;
mod surface;
mod volume;
mod walk_avx2;

pub use danger::{decay_step, DangerMap, DangerParams, DecayMode, FrameReport, DANGER_ON_HIT};
pub use key::{
    check_resolution, KeyConverter, OcTreeKey, MAX_RESOLUTION, MIN_RESOLUTION, TREE_DEPTH,
    TREE_MAX_VAL,
};
pub use occupancy::{logodds, probability, KeyUpdate, Leaf, OcTree, OccupancyParams};
pub use ray::{cast_ray, compute_ray_keys, walk_ray, Point3f, RayCells, RayHit};
pub use scan::{trace_scan, InsertReport, TracedScan};
pub use surface::{Descent, SurfaceMap, SurfaceNode, SurfaceParams, SurfaceSample};
pub use volume::{DenseMarker, KeyVolume};
