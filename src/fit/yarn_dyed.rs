//! Yarn-dyed colours: stripes and checks are woven from yarns dyed before weaving, so each warp
//! and each weft yarn of the repeat carries a colour of its own, constant along its length. The
//! model's two yarn families have one body colour each; a striped photo (a white weft band across
//! a blue plain weave) then fits neither colour, and the geometry bends to make up for it.
//!
//! Before the winner's polish, one body-colour multiplier (RGB) per yarn of the fit's tile —
//! `n_e` weft rows and `n_a` warp columns — is fitted by Adam on the fit loss from one set of
//! recorded paths (the gradient of the paper's spatially varying colour, §7.2,
//! `texture::texel_gradient`, summed over each yarn's texels). The multipliers are then folded
//! into the family colours (each family's colour becomes its brightest yarn's, every multiplier
//! at most 1, so that no `R^B·m` or `S^B·m` exceeds 1: no energy is created), the rest of the
//! appearance and the radii are polished with the multipliers held (`refine::polish`: the fit
//! before them had bent both to average the stripes), and the multipliers fitted once more: a
//! few re-traces in all. A cloth whose first round gains less than half of [`KEEP_GAIN`] stops
//! after it (one re-trace). It is laid out as a [`BodyTexture`] of one texel per cell whose weft
//! texels are constant along each row and whose warp texels along each column, so `woven render`
//! draws it as it draws any body texture.
//!
//! Skipped where the scene does not need it: the per-yarn colours are kept only when they lower
//! the loss by [`KEEP_GAIN`] (a cloth of two uniform families gains only the noise's share).

use std::sync::atomic::AtomicBool;

use super::anneal::Adam;
use super::evaluator::Evaluator;
use super::refine;
use super::texture::texel_gradient;
use crate::params::{BodyTexture, ClothParams};
use crate::pattern::WeavePattern;
use crate::render::PathCache;

/// The least relative loss reduction for which the per-yarn colours are kept: a fifth (about
/// 1 dB of PSNR). Set before measuring; a uniform cloth's fitted multipliers scatter by the
/// noise and lower the loss by a few per cent.
pub(crate) const KEEP_GAIN: f32 = 0.2;

/// Largest multiplier of a yarn's body colour (as [`BodyTexture`] validates).
const MAX_MULTIPLIER: f32 = 4.0;

/// Rounds of the radius and appearance polish under the first round's colours
/// (`refine::polish`).
const POLISH_ROUNDS: usize = 2;

/// Adam iterations of the per-yarn fit (the spatially varying colour's schedule).
const ITERS: usize = 80;

/// The outcome of [`fit_yarn_colours`]: the texture and the loss before and after it (both of
/// the same recorded paths, so their ratio is the colours' own gain).
pub(crate) struct YarnColours {
    /// One texel per cell: weft texels constant along each row, warp texels along each column.
    pub texture: BodyTexture,
    /// Loss with uniform family colours.
    pub loss_before: f32,
    /// Loss with the per-yarn colours.
    pub loss_after: f32,
}

impl YarnColours {
    /// Whether the colours pay for themselves ([`KEEP_GAIN`]).
    pub fn pays(&self) -> bool {
        self.loss_after.is_finite() && self.loss_after < (1.0 - KEEP_GAIN) * self.loss_before
    }

    /// One line for the user: the loss before and after, and each yarn's multiplier (mean over
    /// RGB).
    pub fn describe(&self) -> String {
        let (rows, cols) = self.yarns();
        let list = |v: &[[f32; 3]]| {
            v.iter().map(|c| format!("{:.2}", c.iter().sum::<f32>() / 3.0)).collect::<Vec<_>>().join(" ")
        };
        format!(
            "yarn-dyed colours: each yarn of the repeat keeps its own body colour (loss {:.3e} -> {:.3e}); brightness against the family colour, weft rows [{}], warp columns [{}]",
            self.loss_before,
            self.loss_after,
            list(&rows),
            list(&cols)
        )
    }

    /// The multipliers of the weft rows and the warp columns (each at most 1: the family colour
    /// is its brightest yarn's).
    pub fn yarns(&self) -> (Vec<[f32; 3]>, Vec<[f32; 3]>) {
        let t = &self.texture;
        let w = t.width as usize;
        let rows = (0..t.height as usize).map(|y| t.weft[y * w]).collect();
        let cols = (0..w).map(|x| t.warp[x]).collect();
        (rows, cols)
    }
}

/// Preference of a pattern that repeats with the weave's own repeat: another pattern of the
/// colour tile must score a loss below this fraction of the best weave-periodic one to win.
const WEAVE_PREFERENCE: f32 = 0.9;

/// The finish of a prepared photo's colours: per-yarn colours ([`fit_yarn_colours`]) where they
/// pay. Where preparation found that the colours repeat over more yarns than the weave
/// (`weave = Some([n_e, n_a])`, `prep::colour_repeat`), the fit ran on the colours' tile with one
/// colour per family, and a pattern found there may have taken colour checks for cells: each
/// weave-repeat block of the fitted pattern, tiled over the colour tile (a weave, no yarn
/// floating over it), is scored with its yarn colours beside the fitted pattern, and a
/// weave-periodic pattern wins unless the fitted one scores below [`WEAVE_PREFERENCE`] of it.
/// Returns the cloth and a note for the user where per-yarn colours were kept.
pub(crate) fn finish_colours(
    ev: &Evaluator,
    cloth: &ClothParams,
    weave: Option<[usize; 2]>,
    lm_iters: usize,
    stop: &AtomicBool,
) -> (ClothParams, Option<String>) {
    let score = |c: &ClothParams| {
        let (dyed, found) = fit_yarn_colours(ev, c, lm_iters, stop);
        if found.pays() {
            (found.loss_after, dyed, Some(found.describe()))
        } else {
            (found.loss_before, c.clone(), None)
        }
    };
    let fitted = score(cloth);
    let blocks = weave.map(|w| weave_blocks(&cloth.pattern, w)).unwrap_or_default();
    if blocks.is_empty() {
        return (fitted.1, fitted.2);
    }
    let best = blocks
        .into_iter()
        .map(|p| score(&ClothParams { pattern: p, body_texture: None, ..cloth.clone() }))
        .min_by(|a, b| a.0.total_cmp(&b.0));
    match best {
        Some(b) if fitted.0 >= WEAVE_PREFERENCE * b.0 || fitted.0.is_nan() => {
            let note = format!(
                "the colours repeat over {}×{} yarns, the weave over {}×{}: the pattern {} repeats with the weave (loss {:.3e}; the colour tile's own pattern {} scored {:.3e}){}",
                cloth.pattern.n_e(),
                cloth.pattern.n_a(),
                weave.map_or(0, |w| w[0]),
                weave.map_or(0, |w| w[1]),
                b.1.pattern.reduced(),
                b.0,
                cloth.pattern,
                fitted.0,
                b.2.map(|d| format!("; {d}")).unwrap_or_default()
            );
            (b.1, Some(note))
        }
        _ => (fitted.1, fitted.2),
    }
}

/// The weave-repeat blocks (`weave` = `[n_e, n_a]`) of `pattern`, each tiled over `pattern`'s
/// tile, that are weaves (no yarn floating over the tile) and differ from `pattern`; empty where
/// `pattern` already repeats with the weave or the tile is no multiple of it.
fn weave_blocks(pattern: &WeavePattern, weave: [usize; 2]) -> Vec<WeavePattern> {
    let (n_e, n_a) = (pattern.n_e(), pattern.n_a());
    let [we, wa] = weave;
    if we == 0 || wa == 0 || n_e % we != 0 || n_a % wa != 0 || (we, wa) == (n_e, n_a) {
        return Vec::new();
    }
    let mut out: Vec<WeavePattern> = Vec::new();
    for i0 in (0..n_e).step_by(we) {
        for j0 in (0..n_a).step_by(wa) {
            let rows: Vec<Vec<bool>> =
                (0..n_e).map(|i| (0..n_a).map(|j| pattern.get(i0 + i % we, j0 + j % wa)).collect()).collect();
            let Ok(p) = WeavePattern::from_rows_unreduced(&rows) else { continue };
            if p != *pattern && !p.has_unbound_yarn() && !out.contains(&p) {
                out.push(p);
            }
        }
    }
    out
}

/// Fit one body-colour multiplier per yarn of `cloth`'s tile (see the module doc): per-yarn
/// multipliers from the recorded paths, folded into the family colours, the radii and the
/// appearance polished with the multipliers held (`refine::polish`, `lm_iters` per round), then
/// the multipliers again. Returns the cloth with the texture (its family colours those of each family's
/// brightest yarn, so every multiplier is at most 1 and no `R^B·m` or `S^B·m` exceeds 1: no
/// energy is created) and the losses; the caller keeps it when [`YarnColours::pays`].
pub(crate) fn fit_yarn_colours(
    ev: &Evaluator,
    cloth: &ClothParams,
    lm_iters: usize,
    stop: &AtomicBool,
) -> (ClothParams, YarnColours) {
    let (n_e, n_a) = (cloth.pattern.n_e(), cloth.pattern.n_a());
    let mut plain = cloth.clone();
    plain.body_texture = None;
    // One trace serves the loss before and the first round (`trace_mse` is `loss_of` of a record).
    let cache = ev.record(&plain);
    let loss_before = ev.loss_of(&cache, &plain.appearance);
    // Weft row y at 3y.., warp column x at 3(n_e + x)...
    let mut x = vec![1.0f32; 3 * (n_e + n_a)];
    // First round: free multipliers (up to MAX_MULTIPLIER), so a white stripe can leave a blue
    // family colour; then folded, so that the family colour is the brightest yarn's.
    adam_yarns(ev, &cache, &plain, &mut x, (n_e, n_a), [[MAX_MULTIPLIER; 3]; 2]);
    // A cloth whose yarns share their family's colour stops here: the colours alone (same paths,
    // no backdrop solve on either side) gain less than half the keeping threshold.
    let shaded = |x: &[f32]| ev.mse_of(&cache.shade_texture_parts(&plain.appearance, &texture_of(x, n_e, n_a)).0);
    let (first, uniform) = (shaded(&x), shaded(&vec![1.0; x.len()]));
    let gains = first < (1.0 - 0.5 * KEEP_GAIN) * uniform;
    if !gains {
        let texture = texture_of(&x, n_e, n_a);
        return (plain, YarnColours { texture, loss_before, loss_after: loss_before * first / uniform.max(1e-12) });
    }
    let mut dyed = plain.clone();
    fold(&mut dyed, &mut x, n_e);
    dyed.body_texture = Some(texture_of(&x, n_e, n_a));
    // The rest of the appearance (specular, m_r, transmission) and the radii re-fitted under the
    // yarns' colours: the fit before them had bent both to average the stripes.
    refine::polish(ev, &mut dyed, POLISH_ROUNDS, lm_iters, stop);
    let cache = ev.record(&dyed);
    // Second round: multipliers bounded so that no colour exceeds 1.
    let caps = [0, 1].map(|f| {
        let a = &dyed.appearance;
        let (r, s) = if f == 0 { (a.r_b_e, a.s_b_e) } else { (a.r_b_a, a.s_b_a) };
        [0, 1, 2].map(|k| (1.0 / r[k].max(s[k]).max(1e-3)).min(MAX_MULTIPLIER))
    });
    adam_yarns(ev, &cache, &dyed, &mut x, (n_e, n_a), caps);
    fold(&mut dyed, &mut x, n_e);
    let texture = texture_of(&x, n_e, n_a);
    dyed.body_texture = Some(texture.clone());
    let loss_after = ev.trace_mse(&dyed);
    (dyed, YarnColours { texture, loss_before, loss_after })
}

/// Adam on the per-yarn multipliers `x` (the spatially varying colour's schedule) from the
/// recorded paths `cache` of `cloth`: the texel gradient summed over each yarn's texels; channel
/// `k` of a weft multiplier at most `caps[0][k]`, of a warp one `caps[1][k]`.
fn adam_yarns(
    ev: &Evaluator,
    cache: &PathCache,
    cloth: &ClothParams,
    x: &mut [f32],
    (n_e, n_a): (usize, usize),
    caps: [[f32; 3]; 2],
) {
    let n_tex = n_e * n_a;
    let mut adam = Adam::new(x.len());
    let free = vec![true; x.len()];
    for it in 0..ITERS {
        let tex = texture_of(x, n_e, n_a);
        let (img, parts) = cache.shade_texture_parts(&cloth.appearance, &tex);
        let g_texel = texel_gradient(ev, &img, parts, 2 * n_tex * 3);
        let mut g = vec![0.0f32; x.len()];
        for i in 0..n_tex {
            let (col, row) = (i % n_a, i / n_a);
            for c in 0..3 {
                g[3 * row + c] += g_texel[(2 * i) * 3 + c];
                g[3 * (n_e + col) + c] += g_texel[(2 * i + 1) * 3 + c];
            }
        }
        let lr = vec![0.05f32 * 0.3f32.powf(it as f32 / ITERS as f32); x.len()];
        adam.step(x, &g, &lr, &free);
        for (i, v) in x.iter_mut().enumerate() {
            let family = usize::from(i >= 3 * n_e);
            *v = v.clamp(0.0, caps[family][i % 3]);
        }
    }
}

/// Fold each family's largest multiplier (per channel) into its `R^B` and `S^B`, each capped at 1,
/// and divide the multipliers by it: the family colour becomes its brightest yarn's and every
/// multiplier is at most 1.
fn fold(cloth: &mut ClothParams, x: &mut [f32], n_e: usize) {
    let a = &mut cloth.appearance;
    let (rows, cols) = x.split_at_mut(3 * n_e);
    for (yarns, r, s) in [(rows, &mut a.r_b_e, &mut a.s_b_e), (cols, &mut a.r_b_a, &mut a.s_b_a)] {
        for k in 0..3 {
            let m = yarns.iter().skip(k).step_by(3).fold(0.0f32, |m, &v| m.max(v));
            if m <= 0.0 {
                continue;
            }
            r[k] = (r[k] * m).min(1.0);
            s[k] = (s[k] * m).min(1.0);
            yarns.iter_mut().skip(k).step_by(3).for_each(|v| *v /= m);
        }
    }
}

/// The per-yarn multipliers `x` (weft rows, then warp columns, RGB each) as a texture of one
/// texel per cell.
fn texture_of(x: &[f32], n_e: usize, n_a: usize) -> BodyTexture {
    let mut tex = BodyTexture::ones(n_e, n_a, 1);
    for row in 0..n_e {
        for col in 0..n_a {
            let i = row * n_a + col;
            for c in 0..3 {
                tex.weft[i][c] = x[3 * row + c];
                tex.warp[i][c] = x[3 * (n_e + col) + c];
            }
        }
    }
    tex
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::target::fit_scene;
    use crate::image_io::Image;
    use crate::scene::LightRig;

    /// A plain weave over a 4 × 2 tile whose second weft row is dyed at 0.3 of its family's colour: the fit
    /// finds that row darker than the others, keeps the colours, and the loss falls by more than
    /// [`KEEP_GAIN`]; the same cloth without the stripe is left uniform.
    #[test]
    fn a_striped_weft_is_found_and_a_uniform_cloth_is_left_alone() {
        let mut cloth = ClothParams::preset("plain").expect("preset");
        let rows: Vec<Vec<bool>> = (0..4).map(|i| vec![i % 2 == 0, i % 2 == 1]).collect();
        cloth.pattern = WeavePattern::from_rows_unreduced(&rows).expect("pattern");
        let scene = fit_scene(4, 2, 8, 16, 3, &LightRig::default_rig());
        let mut striped = BodyTexture::ones(4, 2, 1);
        for col in 0..2 {
            striped.weft[2 + col] = [0.3, 0.3, 0.3];
        }
        // The targets are traced with other samples than the fit's: the fit sees noise as well.
        let other =
            Evaluator::new(fit_scene(4, 2, 8, 16, 11, &LightRig::default_rig()), Image::filled(16, 32, [0.0; 3]), 2);
        let target = other.record(&cloth).shade_texture_parts(&cloth.appearance, &striped).0;
        let ev = Evaluator::new(scene.clone(), target, 2);
        let (_, found) = fit_yarn_colours(&ev, &cloth, 6, &AtomicBool::new(false));
        assert!(found.pays(), "loss {:.3e} -> {:.3e}", found.loss_before, found.loss_after);
        let (rows, cols) = found.yarns();
        let mean = |c: &[f32; 3]| c.iter().sum::<f32>() / 3.0;
        for (y, r) in rows.iter().enumerate() {
            if y == 1 {
                assert!(mean(r) < 0.6, "row {y}: {r:?}");
            } else {
                assert!((mean(r) - 1.0).abs() < 0.15, "row {y}: {r:?}");
            }
        }
        assert!(cols.iter().all(|c| (mean(c) - 1.0).abs() < 0.15), "warp columns {cols:?}");

        let uniform = other.record(&cloth).shade_texture_parts(&cloth.appearance, &BodyTexture::ones(4, 2, 1)).0;
        let ev = Evaluator::new(scene, uniform, 2);
        let (_, found) = fit_yarn_colours(&ev, &cloth, 6, &AtomicBool::new(false));
        assert!(!found.pays(), "uniform cloth: loss {:.3e} -> {:.3e}", found.loss_before, found.loss_after);
    }

    /// A 4 × 4 tile whose cells took a gingham's red checks for a pattern: its 2 × 2 blocks that
    /// are weaves (the plain weave and its shift) are offered, the blocks where a yarn floats
    /// over the tile are not, and a tile that already repeats with the weave offers nothing.
    #[test]
    fn weave_blocks_of_a_colour_tile() {
        let p = WeavePattern::parse_unreduced("1110/1101/0100/1000").unwrap();
        let blocks = weave_blocks(&p, [2, 2]);
        assert_eq!(blocks.len(), 2, "{blocks:?}");
        assert!(blocks.iter().all(|b| b.reduced().equivalent(&WeavePattern::preset("plain").unwrap())));
        let plain = WeavePattern::parse_unreduced("1010/0101/1010/0101").unwrap();
        assert!(weave_blocks(&plain, [2, 2]).is_empty());
        assert!(weave_blocks(&p, [3, 2]).is_empty());
    }
}
