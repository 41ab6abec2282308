//! Yarn geometry: periodic B-spline centre curves from the weave pattern, the tile BVH, and the
//! implicit plies/fibers, and the optional flyaway fibres.

pub mod bspline;
pub mod hair;
pub mod ply;
pub mod tile;
pub mod yarn;
