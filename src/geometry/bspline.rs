//! Uniform periodic cubic B-splines of one scalar (the yarn height profile `z(s)`).

/// A periodic uniform cubic B-spline `z(s)`, `s ∈ ℝ` with period `period`; control value `k` sits
/// at `s_k = (k + ½)·Δ`, `Δ = period / K`.
///
/// Each segment is cached as the power-basis cubic `c0 + c1·t + c2·t² + c3·t³` of its local
/// parameter `t ∈ [0, 1)` (the de Boor basis multiplied out once per segment): an evaluation is
/// then one Horner scheme instead of twelve basis polynomials and four control look-ups. Yarn
/// geometry evaluates this spline in every closest-point and tube-exit Newton step, which made it
/// a sixth of the render time (docs/benchmarks.md, profile).
#[derive(Clone, Debug)]
pub struct PeriodicBSpline {
    /// Power-basis coefficients `[c0, c1, c2, c3]` of segment `i` (between control values `i`
    /// and `i + 1`).
    coef: Vec<[f32; 4]>,
    period: f32,
    /// Segments per unit `s` (`K / period`).
    du: f32,
}

/// `⌊u⌋` without a libm call: the release build targets baseline x86-64 (no SSE4.1 `roundss`),
/// where `f32::floor` is a function call that showed up at 3 % of a render's profile.
#[inline]
pub fn floor_fast(u: f32) -> f32 {
    // Beyond 2^23 every f32 is an integer already (and `as i32` would saturate).
    if u.is_nan() || u.abs() >= 8_388_608.0 {
        return u;
    }
    let t = u as i32 as f32;
    if t > u {
        t - 1.0
    } else {
        t
    }
}

impl PeriodicBSpline {
    /// Spline through (approximating) `ctrl` over one period.
    pub fn new(ctrl: Vec<f32>, period: f32) -> Self {
        assert!(!ctrl.is_empty() && period > 0.0);
        let k = ctrl.len();
        let c = |i: usize| ctrl[i % k];
        let coef = (0..k)
            .map(|i| {
                let (p0, p1, p2, p3) = (c(i + k - 1), c(i), c(i + 1), c(i + 2));
                // Uniform cubic B-spline (de Boor) segment between control values i and i+1 in the
                // power basis: b0 = (1−t)³/6, b1 = (3t³ − 6t² + 4)/6, b2 = (−3t³ + 3t² + 3t + 1)/6,
                // b3 = t³/6, collected by powers of t.
                [
                    (p0 + 4.0 * p1 + p2) / 6.0,
                    (p2 - p0) / 2.0,
                    (p0 - 2.0 * p1 + p2) / 2.0,
                    (-p0 + 3.0 * p1 - 3.0 * p2 + p3) / 6.0,
                ]
            })
            .collect();
        PeriodicBSpline { coef, du: k as f32 / period, period }
    }

    /// Period length.
    pub fn period(&self) -> f32 {
        self.period
    }

    #[inline]
    fn locate(&self, s: f32) -> (&[f32; 4], f32) {
        let u = s * self.du - 0.5;
        let i = floor_fast(u);
        let t = u - i;
        let k = self.coef.len() as i64;
        (&self.coef[(i as i64).rem_euclid(k) as usize], t)
    }

    /// Value at `s`.
    #[inline]
    pub fn value(&self, s: f32) -> f32 {
        let (c, t) = self.locate(s);
        ((c[3] * t + c[2]) * t + c[1]) * t + c[0]
    }

    /// Value, first and second derivative with respect to `s`.
    #[inline]
    pub fn eval(&self, s: f32) -> (f32, f32, f32) {
        let (c, t) = self.locate(s);
        let v = ((c[3] * t + c[2]) * t + c[1]) * t + c[0];
        let d = ((3.0 * c[3]) * t + 2.0 * c[2]) * t + c[1];
        let dd = (6.0 * c[3]) * t + 2.0 * c[2];
        (v, d * self.du, dd * self.du * self.du)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn constant_is_reproduced_and_periodic() {
        let s = PeriodicBSpline::new(vec![2.0; 12], 10.0);
        for k in 0..50 {
            let (v, d, _) = s.eval(k as f32 * 0.37 - 3.0);
            assert!((v - 2.0).abs() < 1e-5 && d.abs() < 1e-4);
        }
        let s = PeriodicBSpline::new((0..24).map(|k| (k as f32 * 0.7).sin()).collect(), 20.0);
        for k in 0..40 {
            let x = k as f32 * 0.51;
            assert!((s.eval(x).0 - s.eval(x + 20.0).0).abs() < 1e-4);
            assert!((s.eval(x).0 - s.eval(x - 40.0).0).abs() < 1e-4);
        }
    }

    #[test]
    fn power_basis_matches_the_de_boor_basis() {
        let ctrl: Vec<f32> = (0..24).map(|k| (k as f32 * 0.9).cos() * 3.0 + (k % 5) as f32).collect();
        let s = PeriodicBSpline::new(ctrl.clone(), 20.0);
        let k = ctrl.len();
        for j in 0..500 {
            let x = j as f32 * 0.173 - 31.0;
            let u = x * (k as f32 / 20.0) - 0.5;
            let i = u.floor();
            let t = u - i;
            let i = (i as i64).rem_euclid(k as i64) as usize;
            let p = |m: usize| ctrl[m % k];
            let want = (1.0 - t).powi(3) / 6.0 * p(i + k - 1)
                + (3.0 * t * t * t - 6.0 * t * t + 4.0) / 6.0 * p(i)
                + (-3.0 * t * t * t + 3.0 * t * t + 3.0 * t + 1.0) / 6.0 * p(i + 1)
                + t * t * t / 6.0 * p(i + 2);
            assert!((s.value(x) - want).abs() < 1e-5, "{x}: {} vs {want}", s.value(x));
            assert_eq!(s.value(x), s.eval(x).0);
        }
        for u in [-3.5f32, -3.0, -0.2, 0.0, 0.7, 1.0, 2.5, 1e9, -1e9] {
            assert_eq!(floor_fast(u), u.floor(), "{u}");
        }
    }

    #[test]
    fn derivatives_match_finite_differences() {
        let s = PeriodicBSpline::new((0..24).map(|k| (k as f32 * 0.9).cos() * 3.0).collect(), 20.0);
        for k in 0..60 {
            let x = k as f32 * 0.333 + 0.01;
            let h = 1e-3;
            let fd = (s.eval(x + h).0 - s.eval(x - h).0) / (2.0 * h);
            let fdd = (s.eval(x + h).1 - s.eval(x - h).1) / (2.0 * h);
            let (_, d, dd) = s.eval(x);
            assert!((fd - d).abs() < 2e-2 * (1.0 + d.abs()), "{x}: {fd} vs {d}");
            assert!((fdd - dd).abs() < 5e-2 * (1.0 + dd.abs()), "{x}: {fdd} vs {dd}");
        }
    }
}
