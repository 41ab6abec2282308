//! The BYSDF yarn shading model, over `f32` or dual numbers.

pub mod albedo;
pub mod bysdf;
pub mod ggx;
pub mod real;
pub mod reflect_albedo;
