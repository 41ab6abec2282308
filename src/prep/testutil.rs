//! Test-only synthetic woven images: a procedural top-down weave.
//!
//! For pattern `P` (`n_e × n_a`), texture coordinates `(tx, ty)` are in yarn pitches; cell
//! `(i, j) = (⌊ty⌋ mod n_e, ⌊tx⌋ mod n_a)`. Where `P[i][j] = 1` the weft is on top and the cell is
//! shaded as a horizontal yarn (brightness `cos` profile across the yarn, dark gap between
//! neighbouring wefts); otherwise as a vertical (warp) yarn. Yarn boundaries lie at integer
//! texture coordinates. Pixels are 3×3 super-sampled.

use image::Rgb32FImage;
use rand::prelude::*;
use rand_distr::{Distribution, Normal};

pub fn plain() -> Vec<Vec<u8>> {
    vec![vec![1, 0], vec![0, 1]]
}
pub fn basket2() -> Vec<Vec<u8>> {
    vec![vec![1, 1, 0, 0], vec![1, 1, 0, 0], vec![0, 0, 1, 1], vec![0, 0, 1, 1]]
}
pub fn twill22() -> Vec<Vec<u8>> {
    vec![vec![1, 1, 0, 0], vec![0, 1, 1, 0], vec![0, 0, 1, 1], vec![1, 0, 0, 1]]
}
pub fn satin5() -> Vec<Vec<u8>> {
    (0..5).map(|i| (0..5).map(|j| u8::from(j != (2 * i) % 5)).collect()).collect()
}

/// Linear RGB of the weave at texture coordinates (in pitches).
pub fn texture(p: &[Vec<u8>], tx: f64, ty: f64) -> [f32; 3] {
    let (ne, na) = (p.len() as i64, p[0].len() as i64);
    let (ci, cj) = (ty.floor() as i64, tx.floor() as i64);
    let (fx, fy) = (tx - tx.floor(), ty - ty.floor());
    let weft_over = p[ci.rem_euclid(ne) as usize][cj.rem_euclid(na) as usize] == 1;
    let (across, colour) = if weft_over { (fy - 0.5, [0.85f32, 0.6, 0.35]) } else { (fx - 0.5, [0.35f32, 0.55, 0.85]) };
    let half = 0.44;
    if across.abs() > half {
        return [0.03, 0.03, 0.03];
    }
    let b = (0.15 + 0.85 * (std::f64::consts::FRAC_PI_2 * across / half).cos()) as f32;
    [colour[0] * b, colour[1] * b, colour[2] * b]
}

/// Renders a `w × h` image; `map(x, y)` gives the texture coordinates (in pixels of the flat
/// cloth) of image point `(x, y)`; the pitch converts them to yarn units.
pub fn render(p: &[Vec<u8>], pitch: f64, w: u32, h: u32, map: impl Fn(f64, f64) -> (f64, f64)) -> Rgb32FImage {
    supersample(w, h, |x, y| {
        let (tx, ty) = map(x, y);
        texture(p, tx / pitch, ty / pitch)
    })
}

/// A `w × h` image of `shade(x, y)` (image coordinates), 3×3 super-sampled.
fn supersample(w: u32, h: u32, shade: impl Fn(f64, f64) -> [f32; 3]) -> Rgb32FImage {
    let mut img = Rgb32FImage::new(w, h);
    let offs = [-1.0 / 3.0, 0.0, 1.0 / 3.0];
    for (x, y, px) in img.enumerate_pixels_mut() {
        let mut acc = [0.0f32; 3];
        for oy in offs {
            for ox in offs {
                let c = shade(x as f64 + ox, y as f64 + oy);
                for k in 0..3 {
                    acc[k] += c[k] / 9.0;
                }
            }
        }
        px.0 = acc;
    }
    img
}

/// Axis-aligned render.
pub fn render_flat(p: &[Vec<u8>], pitch: f64, w: u32, h: u32) -> Rgb32FImage {
    render(p, pitch, w, h, |x, y| (x, y))
}

/// Render rotated so that the weft runs along `(cos a, sin a)` in the image (a in degrees).
pub fn render_rotated(p: &[Vec<u8>], pitch: f64, w: u32, h: u32, a_deg: f64) -> Rgb32FImage {
    let (s, c) = a_deg.to_radians().sin_cos();
    let (cx, cy) = (w as f64 / 2.0, h as f64 / 2.0);
    render(p, pitch, w, h, move |x, y| {
        let (dx, dy) = (x - cx, y - cy);
        // Inverse rotation: texture = R(-a) (q - c).
        (c * dx + s * dy + 1000.0 * pitch, -s * dx + c * dy + 1000.0 * pitch)
    })
}

pub fn add_noise(img: &Rgb32FImage, sigma: f32, seed: u64) -> Rgb32FImage {
    let mut rng = StdRng::seed_from_u64(seed);
    let n = Normal::new(0.0f32, sigma).unwrap();
    let mut out = img.clone();
    out.iter_mut().for_each(|v| *v += n.sample(&mut rng));
    out
}

pub fn psnr(a: &Rgb32FImage, b: &Rgb32FImage) -> f64 {
    let mse =
        a.as_raw().iter().zip(b.as_raw()).map(|(x, y)| ((x - y) as f64).powi(2)).sum::<f64>() / a.as_raw().len() as f64;
    10.0 * (1.0 / mse).log10()
}

/// A weft-faced twill 1/3 (each weft floats over three warps and under one, the warp cell
/// stepping by one per row) as hairy yarns photographed front-lit: no dark gaps between parallel
/// yarns (neighbours touch; the yarn flanks fall only to `flank` of the crown), and every float
/// darkens toward its ends where it dives under the crossing yarn. The float ends line up along
/// the twill diagonal, so the strongest straight structure is diagonal while the yarn boundaries
/// are soft: what FabricNET W117 and W125 look like. Texture coordinates in pitches.
pub fn soft_twill13(tx: f64, ty: f64, flank: f64) -> [f32; 3] {
    let (ci, cj) = (ty.floor() as i64, tx.floor() as i64);
    let (fx, fy) = (tx - tx.floor(), ty - ty.floor());
    let warp_cell = cj.rem_euclid(4) == ci.rem_euclid(4);
    let crown = |across: f64| flank + (1.0 - flank) * (std::f64::consts::PI * across).cos().max(0.0);
    let b = if warp_cell {
        // One-cell warp float: shaded across x, and pressed down at both ends.
        crown(fx - 0.5) * (0.55 + 0.45 * (std::f64::consts::PI * fy).sin())
    } else {
        // Position along the three-cell float (0 at its left end, 3 at its right end).
        let start = (ci.rem_euclid(4) + 1) as f64;
        let along = (tx - start).rem_euclid(4.0);
        let end_shade = 0.45 + 0.55 * (std::f64::consts::PI * along / 3.0).sin().max(0.0).sqrt();
        crown(fy - 0.5) * end_shade
    };
    let b = b as f32;
    [0.8 * b, 0.82 * b, 0.78 * b]
}

/// Renders `tex(tx, ty)` (texture coordinates in pitches) over a `w × h` image rotated so that the
/// weft runs along `(cos a, sin a)`, `pitch = [warp, weft]` px per yarn (along x, y of the cloth),
/// 3×3 super-sampled.
pub fn render_texture_rotated(
    pitch: [f64; 2],
    w: u32,
    h: u32,
    a_deg: f64,
    tex: impl Fn(f64, f64) -> [f32; 3],
) -> Rgb32FImage {
    let (s, c) = a_deg.to_radians().sin_cos();
    let (cx, cy) = (w as f64 / 2.0, h as f64 / 2.0);
    supersample(w, h, |x, y| {
        let (dx, dy) = (x - cx, y - cy);
        let (tx, ty) = (c * dx + s * dy + 1000.0 * pitch[0], -s * dx + c * dy + 1000.0 * pitch[1]);
        tex(tx / pitch[0], ty / pitch[1])
    })
}

/// A plain weave of soft (hairy) yarns, yarn-dyed in a wide band (a stripe): inside the
/// band `(start, end)` (fractions of the height) both yarn families are `gain` times as
/// bright. The procedural yarns' contrast is scaled by `contrast` around the level 0.3.
/// Axis-aligned, pitch `[x, y]` px.
pub fn striped_plain(
    pitch: [f64; 2],
    w: u32,
    h: u32,
    band: (f64, f64),
    gain: f32,
    contrast: f32,
) -> image::Rgb32FImage {
    let p = plain();
    let mut img = render_texture_rotated(pitch, w, h, 0.0, |tx, ty| texture(&p, tx, ty));
    for (_, y, px) in img.enumerate_pixels_mut() {
        let f = y as f64 / h as f64;
        let g = if f >= band.0 && f < band.1 { gain } else { 1.0 };
        px.0.iter_mut().for_each(|v| *v = g * (0.3 + contrast * (*v - 0.3)));
    }
    img
}

/// A weft-faced satin of hairy yarns, front-lit, axis-aligned: each weft floats over `n − 1`
/// warps and under one, the binding warp stepping `step` warps a row (`step` coprime with `n`).
/// No gaps between neighbouring wefts (the flanks fall only to 0.55 of the crown), every float
/// darkens toward its ends where it dives under the binding warp, and the warp shows at the
/// binding point only as a weak glossy bump inside a weft-shaded cell — so every cell is
/// shaded across y like a weft, as on FabricNET W084 / W086. Fibres: per weft row, noise
/// along x of `sigma`, blurred over 7 px (streaks along the float), plus per-pixel noise
/// `sigma / 4`. `pitch = [warp, weft]` px; yarn boundaries at multiples of the pitch (before the wander).
pub fn hairy_weft_satin(n: usize, step: usize, pitch: [f64; 2], w: u32, h: u32, sigma: f32, seed: u64) -> Rgb32FImage {
    let mut rng = StdRng::seed_from_u64(seed);
    let normal = Normal::new(0.0f32, sigma).unwrap();
    let crown = |across: f64| 0.55 + 0.45 * (std::f64::consts::PI * across).cos().max(0.0);
    let tex = |tx: f64, ty: f64| -> f32 {
        let (ci, cj) = (ty.floor() as i64, tx.floor() as i64);
        let (fx, fy) = (tx - tx.floor(), ty - ty.floor());
        let bind = (step as i64 * ci).rem_euclid(n as i64);
        // Position along the float: 0 at its start (just after the binding warp), n − 1 at its end.
        let along = (cj - bind - 1).rem_euclid(n as i64) as f64 + fx;
        let nf = (n - 1) as f64;
        let b = if along < nf {
            // Pressed down only near its ends (within about a fifth of a pitch).
            let end = along.min(nf - along);
            crown(fy - 0.5) * (1.0 - 0.4 * (-(end / 0.2).powi(2)).exp())
        } else {
            crown(fy - 0.5) * (0.62 + 0.2 * (std::f64::consts::PI * fx).sin())
        };
        b as f32
    };
    // Wandering wefts: each row's float ends wander along x by up to ±0.12 pitch (a sinusoid of
    // 2.3 repeats' wavelength, random phase per row: yarn irregularity, uneven beat-up), and each
    // row is lit by a gain of 0.85–1.15, so no two repeats of pixels are copies.
    let rows = (h as f64 / pitch[1]).ceil() as usize + 2;
    let wave: Vec<(f64, f32)> =
        (0..rows).map(|_| (std::f64::consts::TAU * rng.random::<f64>(), 0.85 + 0.3 * rng.random::<f32>())).collect();
    let lambda = 2.3 * n as f64 * pitch[0];
    let clean = supersample(w, h, |x, y| {
        let ty = y / pitch[1];
        let (phi, gain) = wave[(ty.floor().max(0.0) as usize).min(rows - 1)];
        let shift = 0.12 * pitch[0] * (std::f64::consts::TAU * x / lambda + phi).sin();
        let v = gain * tex((x + shift) / pitch[0], ty);
        [0.8 * v, 0.82 * v, 0.78 * v]
    });
    let hair: Vec<Vec<f32>> = (0..rows)
        .map(|_| {
            let raw: Vec<f32> = (0..w as usize + 6).map(|_| normal.sample(&mut rng)).collect();
            (0..w as usize).map(|x| raw[x..x + 7].iter().sum::<f32>() / 7.0f32.sqrt()).collect()
        })
        .collect();
    let pixel = Normal::new(0.0f32, sigma / 4.0).unwrap();
    let mut img = clean;
    for (x, y, px) in img.enumerate_pixels_mut() {
        let row = (y as f64 / pitch[1]).floor() as usize;
        let v = hair[row][x as usize] + pixel.sample(&mut rng);
        px.0.iter_mut().for_each(|c| *c = (*c + v).max(0.0));
    }
    img
}
