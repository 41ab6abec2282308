//! Spatially varying body colour (paper §7.2): per-texel multipliers of `R^B`/`S^B` fitted by Adam
//! on the fit loss, with the texel derivatives of one set of recorded paths (no re-trace).

use super::anneal::Adam;
use super::evaluator::{block_filter, Blocks, Evaluator};
use crate::image_io::{linear_to_srgb, linear_to_srgb_slope, Image};
use crate::params::{BodyTexture, ClothParams};
use crate::render::TexturePart;

/// Largest texel multiplier.
const MAX_MULTIPLIER: f32 = 4.0;

/// Optimise a body-colour texture (multipliers, `k` texels per cell, initialised to ones) for
/// `cloth` by Adam on the fit loss (step 0.05 decaying to 0.015 over `iters` iterations).
pub(crate) fn fit_texture(ev: &Evaluator, cloth: &ClothParams, k: u32, iters: usize) -> BodyTexture {
    let mut tex = BodyTexture::ones(cloth.pattern.n_e(), cloth.pattern.n_a(), k);
    let mut plain = cloth.clone();
    plain.body_texture = None;
    let cache = ev.record(&plain);
    let n_tex = tex.weft.len();
    // Interleaved like the texel slots: weft texel i at 2i, warp texel i at 2i + 1, RGB each.
    let mut x: Vec<f32> = vec![1.0; 2 * n_tex * 3];
    let mut adam = Adam::new(x.len());
    for it in 0..iters {
        let (img, parts) = cache.shade_texture_parts(&cloth.appearance, &tex);
        let g = texel_gradient(ev, &img, parts, x.len());
        let lr = vec![0.05f32 * 0.3f32.powf(it as f32 / iters as f32); x.len()];
        let free = vec![true; x.len()];
        adam.step(&mut x, &g, &lr, &free);
        x.iter_mut().for_each(|v| *v = v.clamp(0.0, MAX_MULTIPLIER));
        for i in 0..n_tex {
            for c in 0..3 {
                tex.weft[i][c] = x[(2 * i) * 3 + c];
                tex.warp[i][c] = x[(2 * i + 1) * 3 + c];
            }
        }
    }
    tex
}

/// Gradient of the loss w.r.t. the `n` interleaved texel multipliers from the shaded image and
/// its texel parts (each pixel's body term per texel slot): the chain rule through the block
/// mean and the sRGB encoding; clipped pixels carry none.
pub(super) fn texel_gradient(ev: &Evaluator, img: &Image, parts: Vec<TexturePart>, n: usize) -> Vec<f32> {
    let (b, w) = (ev.block(), img.width);
    let blocks = Blocks::new(img.width, img.height, b);
    let f = block_filter(img, b);
    let count = (f.len() * 3).max(1) as f32;
    let inv = blocks.weight();
    let mut g = vec![0.0f32; n];
    for (px, slot, rgb) in parts {
        let Some(fi) = blocks.block_of(px % w, px / w) else { continue };
        let v = img.data[px as usize];
        for c in 0..3 {
            if v[c] > 0.0 && v[c] < 1.0 {
                let (fv, slope) = (f[fi][c], linear_to_srgb_slope(f[fi][c]));
                let e = linear_to_srgb(fv) - ev.target_values()[fi][c];
                g[slot as usize * 3 + c] += 2.0 * e * slope / count * inv * rgb[c];
            }
        }
    }
    g
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::target::fit_scene;
    use crate::scene::LightRig;

    #[test]
    fn texture_fit_darkens_a_uniformly_darker_target() {
        let cloth = ClothParams::preset("plain").expect("preset");
        let scene = fit_scene(2, 2, 8, 2, 4, &LightRig::default_rig());
        let probe = Evaluator::new(scene.clone(), Image::filled(16, 16, [0.0; 3]), 2);
        let mut dark = BodyTexture::ones(2, 2, 1);
        dark.weft.iter_mut().chain(dark.warp.iter_mut()).for_each(|t| *t = [0.5; 3]);
        let target = probe.record(&cloth).shade_texture_parts(&cloth.appearance, &dark).0;
        let ev = Evaluator::new(scene, target, 2);
        let before = ev.trace_mse(&cloth);
        let tex = fit_texture(&ev, &cloth, 1, 60);
        let mean: f32 = tex.weft.iter().chain(&tex.warp).map(|t| t.iter().sum::<f32>() / 3.0).sum::<f32>()
            / (2 * tex.weft.len()) as f32;
        assert!(mean < 0.8, "mean multiplier {mean}");
        let mut fitted = cloth.clone();
        fitted.body_texture = Some(tex);
        let after = ev.trace_mse(&fitted);
        assert!(after < before / 2.0, "loss {before:.3e} -> {after:.3e}");
    }
}
