//! Scalars for shading: `f32` for plain renders and forward-mode dual numbers [`Dual`] for exact
//! derivatives with respect to the appearance parameters (one pass gives the whole gradient).

use std::ops::{Add, AddAssign, Div, Mul, MulAssign, Neg, Sub};

/// A real number type the BYSDF is written over.
pub trait Real:
    Copy
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
    + Mul<f32, Output = Self>
    + Add<f32, Output = Self>
    + AddAssign
    + MulAssign
{
    /// A constant.
    fn c(x: f32) -> Self;
    /// The value.
    fn v(&self) -> f32;
    /// `f(self)` given `f(v)` and `f'(v)` (chain rule for derivative-carrying types).
    fn apply(self, f: f32, df: f32) -> Self;
    /// Square root (derivative clamped at 0).
    fn sqrt(self) -> Self {
        let s = self.v().max(0.0).sqrt();
        self.apply(s, if s > 1e-12 { 0.5 / s } else { 0.0 })
    }
    /// Exponential.
    fn exp(self) -> Self {
        let e = self.v().exp();
        self.apply(e, e)
    }
    /// Larger of `self` and a constant (derivative of the selected branch).
    fn max_c(self, x: f32) -> Self {
        if self.v() >= x {
            self
        } else {
            Self::c(x)
        }
    }
    /// Smaller of `self` and a constant.
    fn min_c(self, x: f32) -> Self {
        if self.v() <= x {
            self
        } else {
            Self::c(x)
        }
    }
    /// Square.
    fn sq(self) -> Self {
        self * self
    }
    /// `1 − self`.
    fn one_minus(self) -> Self {
        -self + 1.0
    }
}

impl Real for f32 {
    #[inline]
    fn c(x: f32) -> Self {
        x
    }
    #[inline]
    fn v(&self) -> f32 {
        *self
    }
    #[inline]
    fn apply(self, f: f32, _df: f32) -> Self {
        f
    }
    #[inline]
    fn sqrt(self) -> Self {
        self.max(0.0).sqrt()
    }
    #[inline]
    fn exp(self) -> Self {
        f32::exp(self)
    }
}

/// Forward-mode dual number with `N` partial derivatives.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Dual<const N: usize> {
    /// Value.
    pub v: f32,
    /// Partial derivatives.
    pub d: [f32; N],
}

impl<const N: usize> Dual<N> {
    /// The `i`-th independent variable with value `v`.
    pub fn var(v: f32, i: usize) -> Self {
        let mut d = [0.0; N];
        d[i] = 1.0;
        Dual { v, d }
    }
}

impl<const N: usize> Real for Dual<N> {
    #[inline]
    fn c(x: f32) -> Self {
        Dual { v: x, d: [0.0; N] }
    }
    #[inline]
    fn v(&self) -> f32 {
        self.v
    }
    #[inline]
    fn apply(self, f: f32, df: f32) -> Self {
        let mut d = self.d;
        d.iter_mut().for_each(|x| *x *= df);
        Dual { v: f, d }
    }
}

impl<const N: usize> Add for Dual<N> {
    type Output = Self;
    #[inline]
    fn add(mut self, o: Self) -> Self {
        self.v += o.v;
        self.d.iter_mut().zip(o.d.iter()).for_each(|(a, b)| *a += b);
        self
    }
}
impl<const N: usize> AddAssign for Dual<N> {
    #[inline]
    fn add_assign(&mut self, o: Self) {
        *self = *self + o;
    }
}
impl<const N: usize> Sub for Dual<N> {
    type Output = Self;
    #[inline]
    fn sub(mut self, o: Self) -> Self {
        self.v -= o.v;
        self.d.iter_mut().zip(o.d.iter()).for_each(|(a, b)| *a -= b);
        self
    }
}
impl<const N: usize> Mul for Dual<N> {
    type Output = Self;
    #[inline]
    #[allow(clippy::suspicious_arithmetic_impl)] // product rule
    fn mul(self, o: Self) -> Self {
        let d = std::array::from_fn(|i| self.d[i] * o.v + o.d[i] * self.v);
        Dual { v: self.v * o.v, d }
    }
}
impl<const N: usize> MulAssign for Dual<N> {
    #[inline]
    fn mul_assign(&mut self, o: Self) {
        *self = *self * o;
    }
}
impl<const N: usize> Div for Dual<N> {
    type Output = Self;
    #[inline]
    #[allow(clippy::suspicious_arithmetic_impl)] // quotient rule
    fn div(self, o: Self) -> Self {
        let inv = 1.0 / o.v;
        let q = self.v * inv;
        let d = std::array::from_fn(|i| (self.d[i] - q * o.d[i]) * inv);
        Dual { v: q, d }
    }
}
impl<const N: usize> Neg for Dual<N> {
    type Output = Self;
    #[inline]
    fn neg(mut self) -> Self {
        self.v = -self.v;
        self.d.iter_mut().for_each(|x| *x = -*x);
        self
    }
}
impl<const N: usize> Mul<f32> for Dual<N> {
    type Output = Self;
    #[inline]
    fn mul(mut self, k: f32) -> Self {
        self.v *= k;
        self.d.iter_mut().for_each(|x| *x *= k);
        self
    }
}
impl<const N: usize> Add<f32> for Dual<N> {
    type Output = Self;
    #[inline]
    fn add(mut self, k: f32) -> Self {
        self.v += k;
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dual_derivatives_match_finite_differences() {
        let f = |x: Dual<2>, y: Dual<2>| ((x * y + 1.0).sqrt() / (x.sq() + 2.0)).exp() * 3.0 - y.one_minus();
        let g = |x: f32, y: f32| ((x * y + 1.0).sqrt() / (x * x + 2.0)).exp() * 3.0 - (1.0 - y);
        let (x, y) = (0.7, 1.3);
        let r = f(Dual::var(x, 0), Dual::var(y, 1));
        let h = 1e-3;
        let dx = (g(x + h, y) - g(x - h, y)) / (2.0 * h);
        let dy = (g(x, y + h) - g(x, y - h)) / (2.0 * h);
        assert!((r.v - g(x, y)).abs() < 1e-6);
        assert!((r.d[0] - dx).abs() < 1e-3 && (r.d[1] - dy).abs() < 1e-3, "{:?} vs {dx} {dy}", r.d);
    }
}
