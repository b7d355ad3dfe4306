//! Point clouds: depth images to points, cropping, statistical outlier removal,
//! voxel-grid down-sampling, surface normals, Euclidean clusters, rigid 3D-3D fits,
//! and the k-d tree they share.

mod clusters;
mod crop;
mod depth;
mod icp;
mod kdtree;
mod normals;
mod outliers;
mod rigid_fit;
mod voxel_grid;

pub use clusters::cluster_points;
pub use crop::{crop_box, crop_sphere};
pub use depth::{depth_to_points, incidence_cosines, BrownConrady, DepthFrame, Intrinsics};
pub use icp::{
    icp_point_to_plane, icp_point_to_plane_interruptible, IcpParams, IcpResult, IcpTarget, Kernel,
    PlaneTarget, SurfaceCursor, ADAPTIVE_HUBER_SIGMAS,
};
pub use kdtree::KdTree;
pub use normals::{estimate_normals, estimate_normals_interruptible};
pub use outliers::{statistical_outliers, statistical_outliers_interruptible, OutlierParams};
pub use rigid_fit::{rigid_fit, rigid_fit_ransac, rigid_fit_ransac_interruptible, RansacFit};
pub use voxel_grid::{pack_cell, voxel_codes, voxel_downsample, voxel_means};
