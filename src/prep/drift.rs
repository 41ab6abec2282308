//! How the photo departs *slowly* from one periodic repeat on a straight lattice: where each
//! repeat sits (gentle waviness, a period a fraction of a pixel off accumulated over the photo,
//! a slight bow the homography does not hold). Preparation measures it while it aligns the repeats
//! ([`super::regularize`]); the mean repeat — what the fit matches — is free of it, and the fit
//! registered back to the whole photo (`fit.png`) puts it back, so that the photo and the fit can
//! be flipped and compared pixel for pixel.
//!
//! **Shift field.** Each repeat's alignment shift `s_t` (rectified pixels, the median over the
//! repeats removed; at most a quarter pitch, so it cannot jump a yarn) is placed at the repeat's
//! centre; between centres the field is bilinear, beyond the outer centres it is held. A photo
//! pixel at rectified `u` shows the mean repeat at `u − s(u)`.
//!
//! **Tried, not kept: an illumination surface.** Each whole repeat's brightness against the mean
//! repeat, fitted with a plane or a quadratic in `ln g`, as a vignetting/uneven-light gain on
//! `fit.png`: on the 30 prepared shared photos it lowered the periodic ceiling (the whole-photo
//! PSNR of the prepared picture itself) on 6 of them, by up to 1.0 dB (brightness that differs
//! between repeats is mostly hair and yarn irregularity, not light); the shift field alone never
//! lowered it by more than 0.1 dB and raised the median from 17.1 to 17.8 dB.

use image::Rgb32FImage;
use serde::Serialize;

use super::image_ops::sample_into;

/// The slow departures of the photo from the periodic mean repeat, in rectified pixels. The
/// default is none.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct RepeatDrift {
    /// Repeat centres along x, ascending (empty: no shift along x).
    pub centres_x: Vec<f64>,
    /// Repeat centres along y, ascending (empty: no shift along y).
    pub centres_y: Vec<f64>,
    /// Shift of the repeat at `(centres_x[i], centres_y[j])`, index `j · nx + i`, rectified pixels.
    pub shifts: Vec<[f32; 2]>,
}

impl RepeatDrift {
    /// The drift of a lattice of `nx × ny` repeats whose centres are `centres_x`/`centres_y` (one
    /// value for an untiled axis); `shifts` row-major, `j · nx + i`.
    pub fn new(centres_x: Vec<f64>, centres_y: Vec<f64>, shifts: Vec<[f32; 2]>) -> Self {
        debug_assert_eq!(shifts.len(), centres_x.len() * centres_y.len());
        Self { centres_x, centres_y, shifts }
    }

    /// The shift `s(u, v)` at rectified pixel `(u, v)`: bilinear between repeat centres, held
    /// beyond the outer ones.
    pub fn shift_at(&self, u: f64, v: f64) -> [f64; 2] {
        let (nx, ny) = (self.centres_x.len(), self.centres_y.len());
        if nx == 0 || ny == 0 || self.shifts.len() != nx * ny {
            return [0.0, 0.0];
        }
        let (i, fx) = bracket(&self.centres_x, u);
        let (j, fy) = bracket(&self.centres_y, v);
        let (i1, j1) = ((i + 1).min(nx - 1), (j + 1).min(ny - 1));
        let s = |i: usize, j: usize| self.shifts[j * nx + i];
        let mut out = [0.0; 2];
        for (k, o) in out.iter_mut().enumerate() {
            let top = (1.0 - fx) * s(i, j)[k] as f64 + fx * s(i1, j)[k] as f64;
            let bot = (1.0 - fx) * s(i, j1)[k] as f64 + fx * s(i1, j1)[k] as f64;
            *o = (1.0 - fy) * top + fy * bot;
        }
        out
    }

    /// Largest shift of any repeat, pixels (what `woven prep` reports).
    pub fn max_shift(&self) -> f64 {
        self.shifts.iter().map(|s| (s[0] as f64).hypot(s[1] as f64)).fold(0.0, f64::max)
    }

    /// `periodic` (an image of the rectified size that repeats on the nominal lattice, e.g. the
    /// regularized image) with the drift put back: pixel `u` takes `periodic(u − s(u))`, bilinear,
    /// clamped to the image.
    pub fn apply(&self, periodic: &Rgb32FImage) -> Rgb32FImage {
        let (w, h) = (periodic.width() as usize, periodic.height() as usize);
        let src = periodic.as_raw();
        let mut out = vec![0.0f32; w * h * 3];
        for (y, row) in out.chunks_mut(w * 3).enumerate() {
            for x in 0..w {
                let (u, v) = (x as f64, y as f64);
                let s = self.shift_at(u, v);
                sample_into(src, w, h, 3, u - s[0], v - s[1], &mut row[x * 3..x * 3 + 3]);
            }
        }
        Rgb32FImage::from_raw(w as u32, h as u32, out).expect("size")
    }
}

/// Index of the centre at or before `x` and the fraction towards the next one (0 beyond the
/// ends: the field is held there).
fn bracket(c: &[f64], x: f64) -> (usize, f64) {
    if c.len() < 2 || x <= c[0] {
        return (0, 0.0);
    }
    let last = c.len() - 1;
    if x >= c[last] {
        return (last, 0.0);
    }
    let i = c.partition_point(|&ci| ci <= x) - 1;
    (i, (x - c[i]) / (c[i + 1] - c[i]).max(1e-9))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shift_is_bilinear_between_centres_and_held_beyond() {
        let cx: Vec<f64> = (0..5).map(|i| 20.0 + 40.0 * i as f64).collect();
        let cy: Vec<f64> = (0..4).map(|j| 25.0 + 50.0 * j as f64).collect();
        let shifts: Vec<[f32; 2]> =
            cy.iter().flat_map(|&y| cx.iter().map(move |&x| [(x / 40.0) as f32, -(y / 50.0) as f32])).collect();
        let d = RepeatDrift::new(cx, cy, shifts);
        // Between centres: the linear field itself.
        let s = d.shift_at(70.0, 60.0);
        assert!((s[0] - 70.0 / 40.0).abs() < 1e-9 && (s[1] + 60.0 / 50.0).abs() < 1e-9, "{s:?}");
        // Beyond the outer centres: held at the last one.
        let s = d.shift_at(-30.0, 400.0);
        assert!((s[0] - 0.5).abs() < 1e-6 && (s[1] + 175.0 / 50.0).abs() < 1e-6, "{s:?}");
        assert!((d.max_shift() - (4.5f64).hypot(3.5)).abs() < 1e-5);
        assert_eq!(RepeatDrift::default().shift_at(3.0, 4.0), [0.0, 0.0]);
    }

    #[test]
    fn apply_reads_the_periodic_image_back_by_the_shift() {
        // A ramp along x and a uniform shift of 2 px over four repeats along x.
        let img = Rgb32FImage::from_fn(40, 10, |x, _| image::Rgb([x as f32 / 40.0; 3]));
        let d = RepeatDrift::new(vec![5.0, 15.0, 25.0, 35.0], vec![5.0], vec![[2.0, 0.0]; 4]);
        let p = d.apply(&img).get_pixel(20, 4).0[0];
        assert!((p - 18.0 / 40.0).abs() < 1e-6, "{p}");
        assert_eq!(RepeatDrift::default().apply(&img), img);
    }
}
