//! # woven
//!
//! Reconstruct woven cloth — weave pattern, yarn geometry (plies, fibers, radii) and BYSDF
//! appearance — from one close-up photo, and re-render it under any light and view.
//!
//! Modules follow the pipeline: [`params`] (Table 1) and [`pattern`]; the forward model in
//! [`geometry`], [`shading`] and [`render`]; the scene in [`scene`].

pub mod geometry;
pub mod image_io;
pub mod io;
pub mod params;
pub mod pattern;
pub mod render;
pub mod scene;
pub mod shading;

pub use image_io::Image;
pub use params::{Appearance, ClothParams, ParamFile};
pub use pattern::WeavePattern;
pub use scene::Scene;
pub mod bench;
pub mod cli;
pub mod net;
pub mod stress;
pub mod prep;
pub mod datagen;
pub mod fit;
pub mod pre;
