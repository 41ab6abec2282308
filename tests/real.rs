//! Real-photo path (issue 14): the capture estimated from the photo, `woven eval --real` on a tiny
//! folder of our own renders, and — when `../shared/data/real` is present — preparation and one fit
//! on the real photos.

use std::path::{Path, PathBuf};
use woven::fit::capture::{estimate_capture, Capture};
use woven::fit::real::{eval_real, periodic_ceiling, RealOptions};
use woven::fit::FitOptions;
use woven::pattern::WeaveClass;
use woven::prep::{prepare, PrepOptions};
use woven::render::{render, RenderOptions};
use woven::scene::{example_cloth, LightRig, Scene};
use woven::{ClothParams, Image};

/// `preset` (the example cloth: plain loosened so its holes show) with `repeats` repeats across a
/// `size`² image under the named rig, rotated by `rot` degrees.
fn rendered(preset: &str, rig: &str, repeats: f32, size: u32, rot: f32, spp: u32) -> Image {
    render_cloth(example_cloth(preset).unwrap(), rig, repeats, size, rot, spp)
}

/// `cloth` rendered as in [`rendered`].
fn render_cloth(cloth: ClothParams, rig: &str, repeats: f32, size: u32, rot: f32, spp: u32) -> Image {
    let mut scene = Scene { width: size, height: size, spp, lights: LightRig::named(rig).unwrap(), ..Scene::default() };
    scene.camera.tiles = repeats;
    scene.camera.rotation_deg = rot;
    render(&cloth, &scene, &RenderOptions::default())
}

#[test]
fn capture_is_estimated_from_renders_under_front_back_and_both() {
    let mut wrong = Vec::new();
    for (preset, repeats, rot) in [("plain", 5.0, 3.0), ("twill22", 2.5, -4.0), ("satin5", 2.2, 0.0)] {
        for (rig, want) in [("front", Capture::Front), ("back", Capture::Back), ("both", Capture::Both)] {
            let img = rendered(preset, rig, repeats, 320, rot, 4);
            let p = prepare(&img.to_rgb32f(), &PrepOptions::default())
                .unwrap_or_else(|e| panic!("{preset} under {rig}: {e}"));
            let est = estimate_capture(&p).unwrap_or_else(|| panic!("{preset} under {rig}: nothing measured"));
            eprintln!(
                "{preset:8} {rig:6}: hole {:.3} centre {:.3} bright {:.2} reach {:.2} -> {}",
                est.hole_luma,
                est.centre_luma,
                est.bright_share,
                est.reach,
                est.capture.name()
            );
            if est.capture != want {
                wrong.push(format!("{preset} under {rig}: {}", est.describe()));
            }
        }
    }
    assert!(wrong.is_empty(), "{wrong:#?}");
}

/// A folder of our own renders with `labels.csv`, plus a photo without cloth and a missing one.
fn synthetic_folder(dir: &Path) {
    std::fs::create_dir_all(dir.join("sub")).unwrap();
    // The preset plain weave's two yarn colours make a misregistered fit visible.
    render_cloth(ClothParams::preset("plain").unwrap(), "front", 4.0, 192, 8.0, 4)
        .save_png(&dir.join("plain.png"))
        .unwrap();
    rendered("twill22", "both", 2.5, 192, 0.0, 4).save_png(&dir.join("sub/twill.png")).unwrap();
    Image::filled(96, 96, [0.4; 3]).save_png(&dir.join("blank.png")).unwrap();
    std::fs::write(
        dir.join("labels.csv"),
        "path,weave_label,note\nplain.png,plain,render\nsub/twill.png,twill,\"render, both lights\"\nblank.png,satin,no cloth\nmissing.png,plain,absent\n",
    )
    .unwrap();
}

fn quick_options(save: Option<PathBuf>) -> RealOptions {
    let mut fit = FitOptions::fast();
    fit.render.px_per_cell = 8;
    fit.joint.iterations = 12;
    fit.control.threads = Some(2);
    RealOptions { fit, estimate_lights: true, limit: None, save }
}

#[test]
fn eval_real_on_a_folder_of_renders() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("photos");
    synthetic_folder(&dir);
    let save = tmp.path().join("out");
    let mut seen = Vec::new();
    let rep = eval_real(&dir, &quick_options(Some(save.clone())), &mut |c| seen.push(c.path.clone())).unwrap();
    assert_eq!(seen, ["plain.png", "sub/twill.png", "blank.png", "missing.png"]);
    let c = &rep.cases;
    // The renders are fitted: the capture each was rendered under, the class, registered scores.
    assert_eq!(c[0].capture.map(|k| k.capture), Some(Capture::Front), "{:?}", c[0]);
    assert_eq!(c[1].capture.map(|k| k.capture), Some(Capture::Both), "{:?}", c[1]);
    assert_eq!(c[0].class, Some(WeaveClass::Plain), "{:?}", c[0].error);
    for k in &c[..2] {
        assert!(k.error.is_none(), "{}: {:?}", k.path, k.error);
        let photo = k.photo.expect("scored against the whole photo");
        assert!(photo.psnr_db > 12.0 && photo.ssim.is_finite(), "{}: {photo:?}", k.path);
        assert!(k.crop_psnr_db.unwrap() > 15.0, "{}: {:?}", k.path, k.crop_psnr_db);
        let ceiling = k.ceiling_db.expect("the periodic ceiling of a prepared photo");
        assert!(ceiling.is_finite() && ceiling > 12.0, "{}: ceiling {ceiling}", k.path);
        assert!(k.secs > 0.0);
    }
    // The blank photo fails in preparation, with what to try; the missing one names its file.
    let blank = c[2].error.as_deref().unwrap();
    assert!(blank.contains("no periodic yarn structure") && blank.contains("try"), "{blank}");
    assert!(c[2].secs < 20.0, "a photo without cloth fails in seconds: {:.1} s", c[2].secs);
    assert!(c[3].error.as_deref().unwrap().contains("missing.png"), "{:?}", c[3].error);
    let line = rep.summary_line();
    assert!(line.starts_with("real: n=4 class_acc=") && line.contains(" failed=2 "), "{line}");
    for key in ["median_psnr_db=", "median_crop_psnr_db=", "median_fit_s="] {
        assert!(line.contains(key), "{line}");
    }
    // Outputs: each fit in its folder, fit.png the photo's size, the failed one's overlay.
    let fit_png = image::open(save.join("sub/twill/fit.png")).unwrap();
    assert_eq!((fit_png.width(), fit_png.height()), (192, 192));
    // fit.png is the image the whole-photo figures score (up to its 8-bit rounding); the photo
    // noise of noise.json goes to fit_noise.png, which then differs from it.
    let load = |f: &str| Image::load(&save.join("sub/twill").join(f), 1).unwrap();
    let photo_img = Image::load(&dir.join("sub/twill.png"), 1).unwrap();
    let scored = c[1].photo.unwrap().psnr_db;
    let (clean, noisy) = (load("fit.png"), load("fit_noise.png"));
    assert!((clean.psnr_srgb(&photo_img) - scored).abs() < 0.2, "{} vs {scored}", clean.psnr_srgb(&photo_img));
    assert!(noisy.rmse(&clean) > 1e-3, "fit_noise.png carries the noise: rmse {}", noisy.rmse(&clean));
    // fit_sharp.png: the same registered replica without any blur — the photo's size, as close to
    // fit.png as a blur moves it (a few dB), and at least as sharp (energy in pixel-to-pixel
    // steps): fit.png carries the photo's own blur as the fit measured it, none where the fit saw
    // no more than preparation's.
    let sharp = load("fit_sharp.png");
    assert_eq!((sharp.width, sharp.height), (clean.width, clean.height));
    assert!(sharp.psnr_srgb(&clean) > 15.0, "{}", sharp.psnr_srgb(&clean));
    let roughness = |im: &Image| {
        (1..im.width)
            .map(|x| (0..im.height).map(|y| (im.get(x, y)[1] - im.get(x - 1, y)[1]).abs()).sum::<f32>())
            .sum::<f32>()
    };
    assert!(roughness(&sharp) >= roughness(&clean), "{} vs {}", roughness(&sharp), roughness(&clean));
    // The fit is registered to the photo: on the contact sheet (160 px high, so the plain render's
    // 4 repeats of 2 yarns give a pitch of 20 px) it matches the photo better than itself moved by
    // one yarn, which swaps the yarn on top in every cell.
    let row = c[0].row.as_ref().unwrap();
    let (photo, fit) = (row.crop(0, 0, 160, 160), row.crop(162, 0, 160, 160));
    let shifted = Image::new(160, 160, (0..160 * 160).map(|i| fit.get((i % 160 + 20) % 160, i / 160)).collect());
    let (at, off) = (fit.psnr_srgb(&photo), shifted.psnr_srgb(&photo));
    assert!(at > off + 1.0, "registered {at:.2} dB vs one yarn off {off:.2} dB");
    assert!(save.join("plain/capture.json").is_file() && save.join("blank/prep_grid.png").is_file());
    let sheet = rep.sheet().unwrap();
    assert!(sheet.height >= 3 * 160, "three rows (two fits, one overlay): {}", sheet.height);
}

#[test]
fn the_periodic_ceiling_is_high_on_a_periodic_render_and_falls_with_what_no_tile_holds() {
    // A rotated twill render is periodic: the mean of its aligned repeats, registered back,
    // matches it up to the render noise and the resampling (29.3 dB here; the mean after
    // preparation's σ = pitch/16 blur, the ceiling until session 44, scored 24.8 dB). A stain
    // that no other repeat has (what hair or a wandering yarn is to a real photo) lowers it.
    let img = rendered("twill22", "front", 3.0, 192, 4.0, 16);
    let p = prepare(&img.to_rgb32f(), &PrepOptions::default()).unwrap();
    let clean = periodic_ceiling(&p, &img);
    let mut stained = img.clone();
    for y in 80..104 {
        for x in 90..114 {
            stained.data[(y * 192 + x) as usize] = [0.9, 0.9, 0.9];
        }
    }
    let ps = prepare(&stained.to_rgb32f(), &PrepOptions::default()).unwrap();
    let with_stain = periodic_ceiling(&ps, &stained);
    // Rotated by 12°, the rectified image leaves out a tenth of the photo (its corners): the
    // periodic picture is continued there by whole periods, as fit.png is, not clamped.
    let turned = rendered("twill22", "front", 3.0, 192, 12.0, 16);
    let pt = prepare(&turned.to_rgb32f(), &PrepOptions::default()).unwrap();
    let rotated = periodic_ceiling(&pt, &turned);
    eprintln!("ceiling: clean {clean:.2} dB, stained {with_stain:.2} dB, rotated 12° {rotated:.2} dB");
    assert!(clean > 27.0, "clean periodic render: {clean:.2} dB");
    assert!(rotated > clean - 1.5, "rotated 12°: {rotated:.2} dB vs {clean:.2} dB at 4°");
    assert!(with_stain < clean - 2.0, "stain: {with_stain:.2} dB vs clean {clean:.2} dB");
}

#[test]
fn the_command_prints_the_summary_last_and_refuses_bad_folders() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("photos");
    synthetic_folder(&dir);
    let woven =
        |args: &[&str]| std::process::Command::new(env!("CARGO_BIN_EXE_woven")).args(args).output().expect("run woven");
    let d = dir.to_str().unwrap();
    let save = tmp.path().join("save");
    let out = woven(&[
        "eval",
        "--real",
        d,
        "--limit",
        "1",
        "--iterations",
        "8",
        "--px-per-cell",
        "8",
        "--threads",
        "2",
        "--save",
        save.to_str().unwrap(),
    ]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    let last = stdout.lines().last().unwrap();
    assert!(last.starts_with("real: n=1 class_acc=") && last.contains("failed=0"), "{last}");
    assert!(save.join("sheet.png").is_file());
    // A folder without labels.csv, and --limit 0, are refused with a message.
    let out = woven(&["eval", "--real", tmp.path().to_str().unwrap()]);
    assert!(!out.status.success() && String::from_utf8_lossy(&out.stderr).contains("labels.csv"));
    let out = woven(&["eval", "--real", d, "--limit", "0"]);
    assert!(!out.status.success() && String::from_utf8_lossy(&out.stderr).contains("--limit 0"));
    // `woven fit` on the blank photo fails in seconds, writes the overlay beside --out, says what to try.
    let fit_out = tmp.path().join("fit_blank");
    let t = std::time::Instant::now();
    let out = woven(&["fit", dir.join("blank.png").to_str().unwrap(), "--out", fit_out.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("try") && err.contains("prep-grid.png"), "{err}");
    assert!(t.elapsed().as_secs_f64() < 30.0 && tmp.path().join("fit_blank.prep-grid.png").is_file());
    assert!(!fit_out.exists(), "no output folder for a refused photo");
}

/// The shared real photos (not in the repository): `$WOVEN_SHARED/data/real`, else
/// `../shared/data/real` beside the repository.
fn shared_real() -> Option<PathBuf> {
    let root = std::env::var_os("WOVEN_SHARED")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared"));
    let dir = root.join("data/real");
    dir.join("labels.csv").is_file().then_some(dir)
}

#[test]
fn real_photos_prepare_or_fail_in_seconds_with_what_to_try() {
    let Some(dir) = shared_real() else {
        eprintln!("skipped: no ../shared/data/real (set WOVEN_SHARED to the shared folder to run it)");
        return;
    };
    let labels = woven::fit::real::read_labels(&dir).unwrap();
    assert!(labels.len() >= 30, "{}", labels.len());
    let mut prepared = 0;
    for l in &labels {
        let img = Image::load(&dir.join(&l.path), 16).unwrap();
        let t = std::time::Instant::now();
        match prepare(&img.to_rgb32f(), &PrepOptions::default()) {
            Ok(p) => {
                prepared += 1;
                assert!(p.n_e.max(p.n_a) <= 12, "{}: {}×{}", l.path, p.n_e, p.n_a);
                let est = estimate_capture(&p);
                eprintln!("{}: {}×{} {}", l.path, p.n_e, p.n_a, est.map_or("-".into(), |e| e.describe()));
            }
            Err(e) => {
                let msg = e.to_string();
                eprintln!("{}: {msg}", l.path);
                assert!(msg.contains("try"), "{}: {msg}", l.path);
            }
        }
        assert!(t.elapsed().as_secs_f64() < 60.0, "{}: {:.1} s", l.path, t.elapsed().as_secs_f64());
    }
    eprintln!("{prepared} of {} real photos prepared", labels.len());
    assert!(prepared >= 4, "{prepared}");
}

#[test]
fn one_real_photo_is_fitted_and_scored() {
    let Some(dir) = shared_real() else {
        eprintln!("skipped: no ../shared/data/real (set WOVEN_SHARED to the shared folder to run it)");
        return;
    };
    // A label file of one plain-weave photo whose repeat preparation finds (FabricNET W013).
    let tmp = tempfile::tempdir().unwrap();
    let one = tmp.path().join("one");
    std::fs::create_dir_all(&one).unwrap();
    std::fs::copy(dir.join("fabricnet/W013.jpg"), one.join("W013.jpg")).unwrap();
    std::fs::write(one.join("labels.csv"), "path,weave_label\nW013.jpg,plain\n").unwrap();
    let rep = eval_real(&one, &quick_options(None), &mut |_| {}).unwrap();
    let c = &rep.cases[0];
    assert!(c.error.is_none(), "{:?}", c.error);
    let p = c.photo.unwrap();
    eprintln!("{}", rep.summary_line());
    assert!(p.psnr_db.is_finite() && p.psnr_db > 10.0 && p.ssim.is_finite(), "{p:?}");
}
