//! Uniform periodic cubic B-splines of one scalar (the yarn height profile `z(s)`).

/// A periodic uniform cubic B-spline `z(s)`, `s ∈ ℝ` with period `period`; control value `k` sits
/// at `s_k = (k + ½)·Δ`, `Δ = period / K`.
#[derive(Clone, Debug)]
pub struct PeriodicBSpline {
    ctrl: Vec<f32>,
    period: f32,
}

impl PeriodicBSpline {
    /// Spline through (approximating) `ctrl` over one period.
    pub fn new(ctrl: Vec<f32>, period: f32) -> Self {
        assert!(!ctrl.is_empty() && period > 0.0);
        PeriodicBSpline { ctrl, period }
    }

    /// Period length.
    pub fn period(&self) -> f32 {
        self.period
    }

    fn locate(&self, s: f32) -> (usize, f32) {
        let k = self.ctrl.len();
        let u = s * (k as f32 / self.period) - 0.5;
        let i = u.floor();
        let t = u - i;
        ((i as i64).rem_euclid(k as i64) as usize, t)
    }

    fn c(&self, i: usize) -> f32 {
        self.ctrl[i % self.ctrl.len()]
    }

    /// Value, first and second derivative with respect to `s`.
    pub fn eval(&self, s: f32) -> (f32, f32, f32) {
        let (i, t) = self.locate(s);
        let k = self.ctrl.len();
        let (p0, p1, p2, p3) = (self.c(i + k - 1), self.c(i), self.c(i + 1), self.c(i + 2));
        let t2 = t * t;
        let t3 = t2 * t;
        // Uniform cubic B-spline basis (de Boor), segment between control values i and i+1.
        let b0 = (1.0 - t).powi(3) / 6.0;
        let b1 = (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0;
        let b2 = (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0;
        let b3 = t3 / 6.0;
        let d0 = -(1.0 - t).powi(2) / 2.0;
        let d1 = (3.0 * t2 - 4.0 * t) / 2.0;
        let d2 = (-3.0 * t2 + 2.0 * t + 1.0) / 2.0;
        let d3 = t2 / 2.0;
        let e0 = 1.0 - t;
        let e1 = 3.0 * t - 2.0;
        let e2 = -3.0 * t + 1.0;
        let e3 = t;
        let du = k as f32 / self.period;
        let v = b0 * p0 + b1 * p1 + b2 * p2 + b3 * p3;
        let d = (d0 * p0 + d1 * p1 + d2 * p2 + d3 * p3) * du;
        let dd = (e0 * p0 + e1 * p1 + e2 * p2 + e3 * p3) * du * du;
        (v, d, dd)
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
