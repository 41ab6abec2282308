//! Preparation on forward-model renders with known truth: rotation, pitch, minimum pattern size.

use woven::prep::{prepare, PrepError, PrepOptions};
use woven::render::{render, RenderOptions};
use woven::scene::{LightRig, Scene};
use woven::{ClothParams, Image};

/// Renders `preset` with `repeats` pattern repeats across a `size`² image, rotated by `rot` degrees.
/// In a basket weave the paired yarns read as one yarn of twice the pitch in the intensity profile
/// under the asymmetric front light (this gave 2×4 instead of 4×4); the edge spectrum finds the pitch.
#[test]
fn basket_weave_grid() {
    let img = rendered("basket2", 3.0, 320, 0.0);
    let p = prepare(&img.to_rgb32f(), &PrepOptions::default()).unwrap();
    assert_eq!((p.n_e, p.n_a), (4, 4));
}

fn rendered(preset: &str, repeats: f32, size: u32, rot: f32) -> Image {
    let cloth = ClothParams::preset(preset).unwrap();
    let mut scene =
        Scene { width: size, height: size, spp: 2, lights: LightRig::named("front").unwrap(), ..Scene::default() };
    scene.camera.tiles = repeats;
    scene.camera.rotation_deg = rot;
    render(&cloth, &scene, &RenderOptions::default())
}

#[test]
fn rotation_pitch_and_pattern_size_are_recovered_from_renders() {
    // (preset, n, repeats across 320 px, rotation): pitch = 320 / (repeats·n) px. With fewer than ~2
    // repeats left after the rotation crop the period cannot be confirmed (documented in docs/prep.md).
    let cases = [
        ("plain", 2, 5.0, 0.0),
        ("plain", 2, 3.0, -12.0),
        ("twill22", 4, 2.5, 8.0),
        ("twill22", 4, 2.2, -4.0),
        ("twill22", 4, 4.0, 3.0),
        ("satin5", 5, 2.0, 5.0),
        ("satin5", 5, 2.2, 0.0),
        ("plain", 2, 8.0, 10.0),
    ];
    let mut failures = Vec::new();
    for (preset, n, repeats, rot) in cases {
        let img = rendered(preset, repeats, 320, rot);
        let p = match prepare(&img.to_rgb32f(), &PrepOptions::default()) {
            Ok(p) => p,
            Err(e) => {
                failures.push(format!("{preset} {repeats}x rot {rot}: {e}"));
                continue;
            }
        };
        let pitch = 320.0 / (repeats * n as f32);
        // The renderer rotates the cloth by +rot in the image; prep reports the angle it found.
        let ok_angle = (p.angle_deg.abs() - rot.abs()).abs() < 0.5;
        let ok_pitch = [p.pitch_x, p.pitch_y].iter().all(|got| (got - pitch).abs() / pitch < 0.02);
        let ok_size = (p.n_e, p.n_a) == (n, n);
        if !(ok_angle && ok_pitch && ok_size) {
            failures.push(format!(
                "{preset} {repeats}x rot {rot}: angle {:.2}, pitch {:.1}x{:.1} (want {pitch:.1}), size {}x{} (want {n}x{n})",
                p.angle_deg, p.pitch_x, p.pitch_y, p.n_e, p.n_a
            ));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
fn uniform_and_noise_images_have_no_yarn_structure() {
    let flat = Image::filled(128, 128, [0.3; 3]);
    assert!(matches!(prepare(&flat.to_rgb32f(), &PrepOptions::default()), Err(PrepError::NoStructure)));
    let mut h = 12345u64;
    let noise: Vec<[f32; 3]> = (0..128 * 128)
        .map(|_| {
            h = h.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            let v = (h >> 40) as f32 / (1u64 << 24) as f32;
            [v, v, v]
        })
        .collect();
    let e = prepare(&Image::new(128, 128, noise).to_rgb32f(), &PrepOptions::default()).unwrap_err();
    assert_eq!(e.to_string(), "no periodic yarn structure found");
}
