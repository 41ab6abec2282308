//! Numeric helpers shared by every stage, one copy each: dense linear algebra ([`linalg`]:
//! homographies, symmetric eigen-decomposition, Cholesky solves), Levenberg–Marquardt
//! minimisation ([`lm`]) and area-weighted resampling ([`resample`]).

pub mod linalg;
pub mod lm;
pub mod resample;
