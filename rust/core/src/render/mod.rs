//! Images of triangle meshes: a z-buffer rasterizer for depth, labels and shaded colour
//! ([`Rasterizer`]), and the resampling that turns a pinhole render into a distorted
//! lens's image ([`remap_bilinear`], [`remap_nearest`], [`remap_depth`]).
//!
//! The simulated cell's cameras use them in place of a general-purpose renderer: the
//! depth is exact geometry (perspective-correct, pixel (u, v) centred at (u, v) as
//! OpenCV's convention), and a 512×424 frame of a robot cell takes a few milliseconds.

mod lens;
mod raster;

pub use lens::{remap_bilinear, remap_depth, remap_nearest, PixelMap};
pub use raster::{Light, Mesh, Pinhole, Rasterizer, Render};
