//! Numeric helpers shared by every stage, one copy each: dense linear algebra ([`linalg`]:
//! homographies, symmetric eigen-decomposition, Cholesky solves), Levenberg–Marquardt
//! minimisation ([`lm`]), area-weighted resampling ([`resample`]) and the 2-D FFT with the Hann
//! window ([`fft`]).

pub mod fft;
pub mod linalg;
pub mod lm;
pub mod resample;
