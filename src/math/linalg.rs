//! Small dense linear algebra (no external LA crate), the one copy every stage uses.
//!
//! * 3×3 homographies: product, inverse, point mapping (photo rectification).
//! * A cyclic Jacobi eigen-solver for small symmetric matrices, used for the least-squares
//!   vanishing point (smallest eigenvector of a 3×3 scatter matrix), for the Rayleigh–Ritz step of
//!   the Kernel-PCA subspace iteration and for the pseudo-inverse of the fit's Fisher matrix.
//! * [`cholesky_solve`]: symmetric positive definite systems (the damped normal equations of
//!   Levenberg–Marquardt, [`crate::math::lm`]).

/// A 3×3 projective transform, row-major, acting on column vectors `(x, y, 1)`.
pub type Homography = [[f64; 3]; 3];

/// The identity transform.
pub const IDENTITY: Homography = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

/// Matrix product `a · b`.
pub fn mat3_mul(a: &Homography, b: &Homography) -> Homography {
    let mut r = [[0.0; 3]; 3];
    for (i, row) in r.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    r
}

/// Inverse by the adjugate; `None` when (nearly) singular.
pub fn mat3_inv(m: &Homography) -> Option<Homography> {
    let c00 = m[1][1] * m[2][2] - m[1][2] * m[2][1];
    let c01 = m[1][2] * m[2][0] - m[1][0] * m[2][2];
    let c02 = m[1][0] * m[2][1] - m[1][1] * m[2][0];
    let det = m[0][0] * c00 + m[0][1] * c01 + m[0][2] * c02;
    let scale = m.iter().flatten().fold(0.0f64, |a, v| a.max(v.abs()));
    if !det.is_finite() || det.abs() <= 1e-12 * scale.powi(3).max(1e-300) {
        return None;
    }
    let inv_det = 1.0 / det;
    Some([
        [
            c00 * inv_det,
            (m[0][2] * m[2][1] - m[0][1] * m[2][2]) * inv_det,
            (m[0][1] * m[1][2] - m[0][2] * m[1][1]) * inv_det,
        ],
        [
            c01 * inv_det,
            (m[0][0] * m[2][2] - m[0][2] * m[2][0]) * inv_det,
            (m[0][2] * m[1][0] - m[0][0] * m[1][2]) * inv_det,
        ],
        [
            c02 * inv_det,
            (m[0][1] * m[2][0] - m[0][0] * m[2][1]) * inv_det,
            (m[0][0] * m[1][1] - m[0][1] * m[1][0]) * inv_det,
        ],
    ])
}

/// Maps the point `(x, y)` through `h` (with the projective division).
#[inline]
pub fn apply(h: &Homography, x: f64, y: f64) -> (f64, f64) {
    let w = h[2][0] * x + h[2][1] * y + h[2][2];
    let u = h[0][0] * x + h[0][1] * y + h[0][2];
    let v = h[1][0] * x + h[1][1] * y + h[1][2];
    (u / w, v / w)
}

/// Translation by `(tx, ty)`.
pub fn translation(tx: f64, ty: f64) -> Homography {
    [[1.0, 0.0, tx], [0.0, 1.0, ty], [0.0, 0.0, 1.0]]
}

/// Divides `h` by `h[2][2]` (when that is not ~0) so homographies compare and print nicely.
pub fn normalize(h: &Homography) -> Homography {
    let s = h[2][2];
    if s.abs() < 1e-15 {
        return *h;
    }
    let mut r = *h;
    r.iter_mut().flatten().for_each(|v| *v /= s);
    r
}

/// Cross product of homogeneous 3-vectors (line through two points / intersection of two lines).
#[inline]
pub fn cross3(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

/// Eigen-decomposition of the symmetric `n×n` matrix `a` (row-major) by cyclic Jacobi rotations.
/// Returns `(eigenvalues, eigenvectors)` sorted by decreasing eigenvalue; eigenvector `k` is
/// `vecs[k]`. Cost O(n³) per sweep: meant for n ≲ 32.
pub fn sym_eigen(a: &[f64], n: usize) -> (Vec<f64>, Vec<Vec<f64>>) {
    let mut m = a.to_vec();
    let mut v = vec![0.0; n * n];
    for i in 0..n {
        v[i * n + i] = 1.0;
    }
    for _sweep in 0..60 {
        let off: f64 = (0..n)
            .flat_map(|i| (0..n).filter(move |&j| j != i).map(move |j| (i, j)))
            .map(|(i, j)| m[i * n + j] * m[i * n + j])
            .sum();
        let diag: f64 = (0..n).map(|i| m[i * n + i] * m[i * n + i]).sum();
        if off <= 1e-26 * diag.max(1e-300) {
            break;
        }
        for p in 0..n {
            for q in p + 1..n {
                let apq = m[p * n + q];
                if apq.abs() < 1e-300 {
                    continue;
                }
                let app = m[p * n + p];
                let aqq = m[q * n + q];
                let theta = (aqq - app) / (2.0 * apq);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for k in 0..n {
                    let mkp = m[k * n + p];
                    let mkq = m[k * n + q];
                    m[k * n + p] = c * mkp - s * mkq;
                    m[k * n + q] = s * mkp + c * mkq;
                }
                for k in 0..n {
                    let mpk = m[p * n + k];
                    let mqk = m[q * n + k];
                    m[p * n + k] = c * mpk - s * mqk;
                    m[q * n + k] = s * mpk + c * mqk;
                }
                for k in 0..n {
                    let vkp = v[k * n + p];
                    let vkq = v[k * n + q];
                    v[k * n + p] = c * vkp - s * vkq;
                    v[k * n + q] = s * vkp + c * vkq;
                }
            }
        }
    }
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&i, &j| m[j * n + j].total_cmp(&m[i * n + i]));
    let vals = order.iter().map(|&i| m[i * n + i]).collect();
    let vecs = order.iter().map(|&i| (0..n).map(|k| v[k * n + i]).collect()).collect();
    (vals, vecs)
}

/// Solution of `A x = b` for a symmetric positive definite `A` (row-major `n × n`) by Cholesky
/// factorisation `A = L Lᵀ` and two triangular solves; `None` when `A` is not positive definite
/// (a pivot `≤ 0` or NaN). Only the lower triangle of `A` is read. The operation order is that
/// of the fit's appearance Levenberg–Marquardt, whose results are kept bit for bit.
pub fn cholesky_solve(a: &[f64], b: &[f64], n: usize) -> Option<Vec<f64>> {
    let mut l = vec![0.0f64; n * n];
    for i in 0..n {
        for j in 0..=i {
            let s: f64 = a[i * n + j] - (0..j).map(|k| l[i * n + k] * l[j * n + k]).sum::<f64>();
            if i == j {
                if s.is_nan() || s <= 0.0 {
                    return None;
                }
                l[i * n + i] = s.sqrt();
            } else {
                l[i * n + j] = s / l[j * n + j];
            }
        }
    }
    let mut y = vec![0.0f64; n];
    for i in 0..n {
        y[i] = (b[i] - (0..i).map(|k| l[i * n + k] * y[k]).sum::<f64>()) / l[i * n + i];
    }
    let mut x = vec![0.0f64; n];
    for i in (0..n).rev() {
        x[i] = (y[i] - (i + 1..n).map(|k| l[k * n + i] * x[k]).sum::<f64>()) / l[i * n + i];
    }
    Some(x)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn inverse_roundtrip() {
        let h = [[1.1, 0.05, 3.0], [-0.02, 0.95, -7.0], [1e-4, -2e-4, 1.0]];
        let hi = mat3_inv(&h).unwrap();
        let p = mat3_mul(&h, &hi);
        for (i, row) in p.iter().enumerate() {
            for (j, v) in row.iter().enumerate() {
                let e = if i == j { 1.0 } else { 0.0 };
                assert!((v - e).abs() < 1e-12, "{p:?}");
            }
        }
        let (x, y) = apply(&h, 10.0, 20.0);
        let (bx, by) = apply(&hi, x, y);
        assert!((bx - 10.0).abs() < 1e-9 && (by - 20.0).abs() < 1e-9);
        assert!(mat3_inv(&[[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [0.0, 0.0, 1.0]]).is_none());
    }

    #[test]
    fn cholesky_solves_spd_and_refuses_indefinite() {
        // Hand-computed: L = [[2, 0, 0], [1, 2, 0], [0, 0.5, √2.75]], A x = b for x = (1, −2, 0.5).
        let a = [4.0, 2.0, 0.0, 2.0, 5.0, 1.0, 0.0, 1.0, 3.0];
        let b = [0.0, -7.5, -0.5];
        let x = cholesky_solve(&a, &b, 3).expect("SPD");
        x.iter().zip([1.0, -2.0, 0.5]).for_each(|(u, v)| assert!((u - v).abs() < 1e-12, "{x:?}"));
        // A 1×1 system and an exactly representable 2×2 one.
        assert_eq!(cholesky_solve(&[4.0], &[2.0], 1), Some(vec![0.5]));
        assert_eq!(cholesky_solve(&[4.0, 2.0, 2.0, 2.0], &[6.0, 4.0], 2), Some(vec![1.0, 1.0]));
        // Indefinite, singular and NaN matrices are refused.
        assert!(cholesky_solve(&[1.0, 2.0, 2.0, 1.0], &[1.0, 1.0], 2).is_none());
        assert!(cholesky_solve(&[1.0, 1.0, 1.0, 1.0], &[1.0, 1.0], 2).is_none());
        assert!(cholesky_solve(&[f64::NAN], &[1.0], 1).is_none());
    }

    #[test]
    fn jacobi_eigen() {
        // A = Q diag(5, 2, -1) Q^T for a known rotation Q.
        let (c, s) = (0.6f64, 0.8f64);
        let q = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]];
        let d = [5.0, 2.0, -1.0];
        let mut a = [0.0; 9];
        for i in 0..3 {
            for j in 0..3 {
                a[i * 3 + j] = (0..3).map(|k| q[i][k] * d[k] * q[j][k]).sum();
            }
        }
        let (vals, vecs) = sym_eigen(&a, 3);
        for (v, e) in vals.iter().zip(d) {
            assert!((v - e).abs() < 1e-10, "{vals:?}");
        }
        // First eigenvector is ±(c, s, 0).
        assert!((vecs[0][0].abs() - c).abs() < 1e-9 && (vecs[0][1].abs() - s).abs() < 1e-9);
    }
}
