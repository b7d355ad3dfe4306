//! The robot's geometry: kinematics, padded link capsules, self-filter, collision,
//! clearance and the danger cost of motions (Paper II §3, §6-7).

mod body;
mod capsule;
mod chain;
mod collision;
mod fit;
// Also a public namespace: `robot::follower::Follower` is a path the binding uses.
pub mod follower;
mod model;
mod self_filter;
mod voxel_index;

pub use body::{AxisBounds, Body, BodyBoxContact, BodyShape, ContactStep, NearestContact};
pub use capsule::{
    closest_parameter_on_segment, lerp, point_segment_distance_squared, segment_box_closest,
    segment_segment_closest, Capsule,
};
pub use chain::{Chain, Frame, Joint, JointAxis, JointKind, MAX_ROBOT_LENGTH};
pub use collision::{
    check_configurations, check_motion, clearances, clearances_to_boxes, interpolate,
    motion_danger, robot_within_map, touches_boxes, CheckParams, Contact, MAX_DANGER_POINTS,
    MAX_DANGER_WORK, MAX_MOTION_STEPS,
};
pub use fit::{fit_body, fit_capsule, fit_cylinder, FitShape};
pub use follower::{Follower, Rollout};
pub use model::{LazyPlacement, PlacedBodies, RobotModel};
pub use self_filter::self_filter;
pub use voxel_index::{
    Clearance, ClearanceScratch, SampleVerdict, UndecidedRuns, VoxelIndex, VoxelSource,
    MAX_INDEX_CELLS,
};
