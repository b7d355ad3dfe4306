//! The robot's geometry: kinematics, padded link capsules, self-filter, collision,
//! clearance and the danger cost of motions (Paper II §3, §6-7).

pub mod body;
pub mod capsule;
pub mod chain;
pub mod collision;
pub mod fit;
pub mod follower;
pub mod model;
pub mod self_filter;
pub mod voxel_index;

pub use body::{Body, BodyBoxContact, BodyShape};
pub use capsule::Capsule;
pub use chain::{Chain, Frame, Joint, JointAxis, JointKind};
pub use collision::{
    check_configurations, check_motion, clearances, clearances_to_boxes, interpolate,
    motion_danger, touches_boxes, CheckParams, Contact,
};
pub use fit::{fit_body, fit_capsule, fit_cylinder, FitShape};
pub use follower::{Follower, Rollout};
pub use model::{LazyPlacement, PlacedBodies, RobotModel};
pub use self_filter::self_filter;
pub use voxel_index::{Clearance, SampleVerdict, UndecidedRuns, VoxelIndex, VoxelSource};
