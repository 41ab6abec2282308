//! Fibers below the pixel footprint sampled in strata of their phase (docs/design.md §1.4): at
//! photo resolution (a few pixels per cell) a few samples per pixel come closer to a supersampled
//! reference than without it, with the same mean, and where the fibers are above a pixel nothing
//! changes, bit for bit.
//!
//! `WOVEN_FOOTPRINT_OUT=DIR` also writes the side-by-side pictures (reference | off | on) and
//! prints the timings.

use std::time::Instant;
use woven::params::ClothParams;
use woven::render::{render, RenderOptions};
use woven::scene::{CameraSpec, LightRig, Scene};
use woven::Image;

/// A scene framing `cells` cells across a `size`-pixel square (`repeat` cells per pattern repeat).
fn scene(size: u32, cells: f32, repeat: f32, spp: u32, filter: bool, lights: &str) -> Scene {
    Scene {
        width: size,
        height: size,
        spp,
        seed: 3,
        camera: CameraSpec { tiles: cells / repeat, offset: [0.13, 0.37], ..CameraSpec::default() },
        lights: lights.parse::<LightRig>().unwrap(),
        footprint_filter: filter,
        ..Scene::default()
    }
}

fn timed(cloth: &ClothParams, s: &Scene) -> (Image, f64) {
    let opts = RenderOptions { threads: Some(2), ..RenderOptions::default() };
    let t = Instant::now();
    let img = render(cloth, s, &opts);
    (img, t.elapsed().as_secs_f64())
}

#[test]
fn filtered_low_spp_renders_come_closer_to_the_supersampled_reference() {
    let out = std::env::var_os("WOVEN_FOOTPRINT_OUT").map(std::path::PathBuf::from);
    let size = if out.is_some() { 96 } else { 48 };
    let ref_spp = if out.is_some() { 256 } else { 64 };
    let mut rows = Vec::new();
    let mut gains = Vec::new();
    for (preset, lights) in [("plain", "front"), ("twill22", "default")] {
        let cloth = ClothParams::preset(preset).unwrap();
        let repeat = cloth.pattern.n_a() as f32;
        for px_per_cell in [3.0f32, 6.0] {
            let cells = size as f32 / px_per_cell;
            let (reference, t_ref) = timed(&cloth, &scene(size, cells, repeat, ref_spp, false, lights));
            let (off, t_off) = timed(&cloth, &scene(size, cells, repeat, 4, false, lights));
            let (on, t_on) = timed(&cloth, &scene(size, cells, repeat, 4, true, lights));
            let (p_off, p_on) = (off.psnr_srgb(&reference), on.psnr_srgb(&reference));
            eprintln!(
                "{preset} {lights} {px_per_cell} px/cell, 4 spp vs {ref_spp} spp: PSNR off {p_off:.2} dB, on {p_on:.2} dB; mean ref {:?} off {:?} on {:?}; \
                 time off {t_off:.2} s, on {t_on:.2} s (reference {t_ref:.1} s)", reference.mean(), off.mean(), on.mean()
            );
            assert!(p_on.is_finite() && p_off.is_finite());
            assert!(
                p_on > p_off + 0.1,
                "{preset} at {px_per_cell} px/cell: the filter should bring 4 spp closer to the reference ({p_on} vs {p_off} dB)"
            );
            gains.push(p_on - p_off);
            rows.push(Image::hstack(&[&reference, &off, &on], 4));
        }
    }
    let mean_gain = gains.iter().sum::<f32>() / gains.len() as f32;
    assert!(mean_gain > 0.5, "mean PSNR gain {mean_gain} dB");
    if let Some(dir) = out {
        std::fs::create_dir_all(&dir).unwrap();
        let refs: Vec<&Image> = rows.iter().collect();
        Image::vstack(&refs, 4).save_png(&dir.join("footprint.png")).unwrap();
    }
}

#[test]
fn detail_above_the_pixel_renders_the_same_bit_for_bit() {
    // 256 px per cell: a pixel is 0.04 units, below half of the preset's fiber period (spacing
    // 2π·r_p/n_f ≈ 0.4, foreshortened at most 5× at the silhouettes): the filter must not touch a
    // single sample.
    let cloth = ClothParams::preset("plain").unwrap();
    let a = render(&cloth, &scene(128, 0.5, 2.0, 2, false, "default"), &RenderOptions::default());
    let b = render(&cloth, &scene(128, 0.5, 2.0, 2, true, "default"), &RenderOptions::default());
    assert_eq!(a.data, b.data);
    // …while at 6 px per cell it does change the picture.
    let cloth = ClothParams::preset("twill22").unwrap();
    let c = render(&cloth, &scene(48, 8.0, 4.0, 4, false, "default"), &RenderOptions::default());
    let d = render(&cloth, &scene(48, 8.0, 4.0, 4, true, "default"), &RenderOptions::default());
    assert_ne!(c.data, d.data);
}

#[test]
fn old_scene_files_filter_and_switching_it_off_round_trips() {
    let s: Scene = serde_json::from_str("{}").unwrap();
    assert!(s.footprint_filter);
    let off = Scene { footprint_filter: false, ..Scene::default() };
    let text = serde_json::to_string(&off).unwrap();
    assert!(text.contains("\"footprint_filter\":false"));
    let back: Scene = serde_json::from_str(&text).unwrap();
    assert!(!back.footprint_filter);
    // The default is not written, so files written with it on read back the same.
    assert!(!serde_json::to_string(&Scene::default()).unwrap().contains("footprint_filter"));
}
