//! # woven
//!
//! Reconstruct woven cloth — weave pattern, yarn geometry (plies, fibers, radii) and BYSDF
//! appearance — from one close-up photo, and re-render it under any light and view.
//!
//! Modules follow the pipeline: [`params`] (Table 1) and [`pattern`]; the forward model in
//! [`geometry`], [`shading`] and [`render`] with its [`scene`]; the synthetic training set in
//! [`datagen`]; the pre-estimator network in [`net`] (glue in [`pre`]); photo preparation in
//! [`prep`]; the reconstruction in [`fit`], with the noise post-estimation in [`noise`] and the
//! geometry export in [`export`]. Shared pieces: [`math`] (linear algebra, Levenberg–Marquardt,
//! resampling), [`image_io`], [`io`] (atomic writes, checked reads), [`plot`] and [`progress`]
//! (the callback through which long operations report, so the library never prints). [`bench`](mod@bench)
//! and [`stress`] back the `woven bench` and `woven stress` commands; the command line itself
//! lives in the binary (`src/cli/`), which has the only terminal and Ctrl-C code.

#![warn(missing_docs)]

pub mod bench;
pub mod datagen;
pub mod export;
pub mod fit;
pub mod geometry;
pub mod image_io;
pub mod io;
pub mod math;
pub mod net;
pub mod noise;
pub mod params;
pub mod pattern;
pub mod plot;
pub mod pre;
pub mod prep;
pub mod progress;
pub mod render;
pub mod scene;
pub mod shading;
pub mod stress;

pub use image_io::Image;
pub use params::{Appearance, ClothParams, ParamFile};
pub use pattern::WeavePattern;
pub use scene::Scene;
