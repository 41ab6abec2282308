//! Forward-model benchmark (`woven bench`): time vs error, thread scaling, re-shading, and what
//! each skip saves. Results are written into a section of `docs/benchmarks.md`.

use crate::image_io::Image;
use crate::params::ClothParams;
use crate::progress::Progress;
use crate::render::{render, Prepared, RenderOptions};
use crate::scene::{CameraSpec, LightRig, Scene};
use anyhow::{Context, Result};
use std::fmt::Write as _;
use std::path::Path;
use std::time::Instant;

/// Replace (or append) the `## {title}` section of a markdown file with `body`.
pub fn replace_section(path: &Path, title: &str, body: &str) -> Result<()> {
    let old = std::fs::read_to_string(path)
        .unwrap_or_else(|_| "# Benchmarks\n\nMachine: 2 cores, 24 GiB (the project's standard machine).\n".into());
    let head = format!("## {title}\n");
    let section = format!("{head}\n{body}\n");
    let new = match old.find(&head) {
        Some(start) => {
            let rest = &old[start + head.len()..];
            let end = rest.find("\n## ").map(|e| start + head.len() + e + 1).unwrap_or(old.len());
            format!("{}{}{}", &old[..start], section, &old[end..])
        }
        None => format!("{}\n\n{section}", old.trim_end()),
    };
    crate::io::write_atomic(path, new.as_bytes()).with_context(|| format!("writing {}", path.display()))
}

fn time<R>(reps: usize, mut f: impl FnMut() -> R) -> (f64, R) {
    let mut best = f64::INFINITY;
    let mut out = None;
    for _ in 0..reps.max(1) {
        let t0 = Instant::now();
        let r = f();
        best = best.min(t0.elapsed().as_secs_f64());
        out = Some(r);
    }
    (best, out.expect("at least one repetition"))
}

fn bench_scene(size: u32, spp: u32, rig: LightRig) -> Scene {
    Scene { width: size, height: size, spp, lights: rig, ..Scene::default() }
}

/// Run the benchmark and return its markdown section (the `woven bench` command prints it and
/// writes it into `docs/benchmarks.md` with [`replace_section`]). Each measurement is announced
/// to `progress` as a message.
pub fn run(quick: bool, progress: &dyn Progress) -> Result<String> {
    let cloth = ClothParams::preset("twill22")?;
    let size = 256;
    let ref_spp = if quick { 256 } else { 1024 };
    let reps = if quick { 1 } else { 3 };
    let mut md = String::new();
    let cmd = if quick { "woven bench --quick" } else { "woven bench" };
    writeln!(md, "Command: `{cmd}` (release build). Scene: twill 2/2, default light rig (ambient + front, back, two sides), orthographic, 2 repeats across, {size}×{size}. Best of {reps} runs.\n")?;
    progress.message(&format!("reference render at {ref_spp} spp …"));
    let (t_ref, reference) =
        time(1, || render(&cloth, &bench_scene(size, ref_spp, LightRig::default_rig()), &RenderOptions::default()));
    writeln!(md, "Reference: {ref_spp} spp, {t_ref:.1} s on 2 threads.\n")?;
    writeln!(md, "### Time vs error\n\n| spp | threads | wall time (s) | RMSE vs reference (linear) | PSNR (sRGB, dB) |\n|---|---|---|---|---|")?;
    for spp in [1u32, 4, 16, 64] {
        for threads in [1usize, 2] {
            let scene = bench_scene(size, spp, LightRig::default_rig());
            let opts = RenderOptions { threads: Some(threads), ..Default::default() };
            let (t, img) = time(reps, || render(&cloth, &scene, &opts));
            writeln!(
                md,
                "| {spp} | {threads} | {t:.3} | {:.4} | {:.1} |",
                img.rmse(&reference),
                img.psnr_srgb(&reference)
            )?;
            progress.message(&format!("{spp} spp, {threads} threads: {t:.3} s"));
        }
    }
    // Re-shading recorded paths vs rendering from scratch.
    writeln!(md, "\n### Re-shading (appearance-only change: no re-tracing)\n\n| image | spp | full render (s) | record paths (s) | re-shade f32 (ms) | re-shade + 30 exact derivatives (ms) | paths' vertices |\n|---|---|---|---|---|---|---|")?;
    let mut other = cloth.appearance.clone();
    other.r_b_e = [0.3, 0.5, 0.7];
    other.alpha_s = 0.6;
    for (sz, spp) in [(64u32, 4u32), (128, 4), (256, 1)] {
        let scene = bench_scene(sz, spp, LightRig::default_rig());
        let prep = Prepared::new(&cloth, &scene, &RenderOptions::default());
        let (t_full, _) = time(reps, || Prepared::new(&cloth, &scene, &RenderOptions::default()).render(&other));
        let (t_rec, cache) = time(1, || prep.record(&cloth.appearance));
        let (t_sh, _) = time(reps.max(3), || cache.shade(&other));
        let (t_d, _) = time(reps, || cache.mse_and_gradient(&other, &Image::filled(sz, sz, [0.1; 3])));
        writeln!(
            md,
            "| {sz}×{sz} | {spp} | {t_full:.3} | {t_rec:.3} | {:.1} | {:.1} | {} |",
            t_sh * 1e3,
            t_d * 1e3,
            cache.vertex_count()
        )?;
    }
    // Skips.
    writeln!(md, "\n### What each skip saves\n\n| skip | without (s) | with (s) | saving | image difference (RMSE) |\n|---|---|---|---|---|")?;
    let front_only = LightRig { ambient: [0.0; 3], lights: LightRig::named("front").expect("rig").lights };
    let scene = bench_scene(size, 4, front_only);
    let (t_no, a) =
        time(reps, || render(&cloth, &scene, &RenderOptions { skip_unlit_transmission: false, ..Default::default() }));
    let (t_yes, b) = time(reps, || render(&cloth, &scene, &RenderOptions::default()));
    writeln!(md, "| no transmission paths when nothing lights the back (front light only, 4 spp) | {t_no:.3} | {t_yes:.3} | {:.0}% | {:.5} |", 100.0 * (1.0 - t_yes / t_no), a.rmse(&b))?;
    let scene = bench_scene(128, 4, LightRig::default_rig());
    let prep = Prepared::new(&cloth, &scene, &RenderOptions::default());
    let cache = prep.record(&cloth.appearance);
    let (t_full, a) = time(reps, || Prepared::new(&cloth, &scene, &RenderOptions::default()).render(&other));
    let (t_re, b) = time(reps.max(3), || cache.shade(&other));
    writeln!(md, "| no re-tracing when only appearance changed (128², 4 spp) | {t_full:.3} | {t_re:.4} | {:.1}% | {:.5} (same paths sampled with θ₀) |", 100.0 * (1.0 - t_re / t_full), a.rmse(&b))?;
    for tiles in [2.0f32, 8.0] {
        let scene = Scene {
            camera: CameraSpec { tiles, ..Default::default() },
            ..bench_scene(size, 4, LightRig::default_rig())
        };
        let whole = RenderOptions { whole_fabric: true, ..Default::default() };
        let (t_w, a) = time(reps, || render(&cloth, &scene, &whole));
        let (t_t, b) = time(reps, || render(&cloth, &scene, &RenderOptions::default()));
        let caps_w = Prepared::new(&cloth, &scene, &whole).geom.capsule_count();
        let caps_t = Prepared::new(&cloth, &scene, &RenderOptions::default()).geom.capsule_count();
        writeln!(md, "| one periodic tile instead of every repeat in view ({tiles} repeats across; {caps_w} → {caps_t} capsules) | {t_w:.3} | {t_t:.3} | {:.0}% | {:.5} |", 100.0 * (1.0 - t_t / t_w), a.rmse(&b))?;
    }
    progress.message("visibility of each appearance parameter …");
    md.push_str(&visibility_table(&cloth)?);
    Ok(md)
}

/// Design decision 4 (docs/design.md) check: does each appearance parameter visibly change the
/// image over its range? RMSE (linear) between renders at the parameter's minimum and maximum,
/// everything else at the preset, for the front-lit and back-lit rigs (re-shaded from one set of
/// recorded paths per rig).
pub fn visibility_table(cloth: &ClothParams) -> Result<String> {
    use crate::params::{ParamKind, N_APPEARANCE, PARAMS};
    let mut md = String::from("\n### Does every parameter change the image? (decision 4)\n\nRMSE between renders with the parameter at its minimum and at its maximum (96×96, 16 spp, twill 2/2 preset otherwise; mean pixel value ≈ 0.1–0.3). `≈0` marks parameters the image cannot determine.\n\n| parameter | range | front rig | back rig |\n|---|---|---|---|\n");
    let rigs = [LightRig::named("front").expect("rig"), LightRig::named("back").expect("rig")];
    let caches: Vec<_> = rigs
        .iter()
        .map(|rig| {
            let scene = bench_scene(96, 16, rig.clone());
            Prepared::new(cloth, &scene, &RenderOptions::default()).record(&cloth.appearance)
        })
        .collect();
    let base = cloth.appearance.to_vec();
    for (i, r) in PARAMS[..N_APPEARANCE].iter().enumerate() {
        if matches!(r.kind, ParamKind::Rgb(1) | ParamKind::Rgb(2)) {
            continue; // colour channels behave alike: report channel 0
        }
        let mut cells = Vec::new();
        for c in &caches {
            let mut lo = base;
            let mut hi = base;
            lo[i] = r.min;
            hi[i] = r.max;
            let d = c
                .shade(&crate::params::Appearance::from_slice(&lo))
                .rmse(&c.shade(&crate::params::Appearance::from_slice(&hi)));
            cells.push(if d < 1e-4 { format!("≈0 ({d:.1e})") } else { format!("{d:.4}") });
        }
        writeln!(md, "| `{}` | [{}, {}] | {} | {} |", r.name, r.min, r.max, cells[0], cells[1])?;
    }
    Ok(md)
}
