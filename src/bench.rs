//! Forward-model benchmark (`woven bench`): time vs error, thread scaling, re-shading, and what
//! each skip saves. Results are written into a section of `docs/benchmarks.md`.

use crate::export::{export, ExportOptions};
use crate::image_io::Image;
use crate::params::{ClothParams, ParamFile};
use crate::progress::Progress;
use crate::render::{render, Prepared, RenderOptions};
use crate::scene::{CameraSpec, LightRig, Scene};
use anyhow::{Context, Result};
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::Command;
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

/// CPU seconds (user + system) of this process and of its waited-for children, from
/// `/proc/self/stat` (fields 14–17: utime, stime, cutime, cstime, in clock ticks of 1/100 s, the
/// `USER_HZ` of every Linux ABI); `None` where that file does not exist. The machine is shared, so
/// wall times move with the load while CPU seconds do not (docs/benchmarks.md compares CPU seconds).
pub fn cpu_seconds() -> Option<(f64, f64)> {
    cpu_seconds_of_stat(&std::fs::read_to_string("/proc/self/stat").ok()?)
}

/// Clock ticks per second of `/proc/self/stat`'s times: `USER_HZ`, fixed at 100 in Linux's
/// user-space interface on every architecture it supports.
const USER_HZ: f64 = 100.0;

/// `(utime + stime, cutime + cstime)` in seconds from the text of a `/proc/PID/stat` file.
fn cpu_seconds_of_stat(stat: &str) -> Option<(f64, f64)> {
    // The command name (field 2) is in parentheses and may hold spaces and parentheses: count
    // after the last ')', where field 3 (state) is the first and utime..cstime are fields 14–17.
    let rest = &stat[stat.rfind(')')? + 1..];
    let f: Vec<f64> = rest.split_whitespace().skip(11).take(4).map(|v| v.parse().unwrap_or(f64::NAN)).collect();
    (f.len() == 4 && f.iter().all(|v| v.is_finite())).then(|| ((f[0] + f[1]) / USER_HZ, (f[2] + f[3]) / USER_HZ))
}

/// The 1-minute load average (`/proc/loadavg`), to print beside wall times.
fn load_average() -> Option<f64> {
    std::fs::read_to_string("/proc/loadavg").ok()?.split_whitespace().next()?.parse().ok()
}

/// [`time`] that also returns the CPU seconds of the fastest repetition (NaN without `/proc`).
fn time_cpu<R>(reps: usize, mut f: impl FnMut() -> R) -> (f64, f64, R) {
    let mut best = (f64::INFINITY, f64::NAN);
    let mut out = None;
    for _ in 0..reps.max(1) {
        let c0 = cpu_seconds();
        let t0 = Instant::now();
        let r = f();
        let t = t0.elapsed().as_secs_f64();
        let cpu = match (c0, cpu_seconds()) {
            (Some(a), Some(b)) => b.0 - a.0,
            _ => f64::NAN,
        };
        if t < best.0 {
            best = (t, cpu);
        }
        out = Some(r);
    }
    (best.0, best.1, out.expect("at least one repetition"))
}

fn bench_scene(size: u32, spp: u32, rig: LightRig) -> Scene {
    Scene { width: size, height: size, spp, lights: rig, ..Scene::default() }
}

/// Image side of the bench scene (pixels).
pub const BENCH_SIZE: u32 = 256;
/// Samples per pixel of the side-by-side comparison with Mitsuba 3 (the "16 spp" row).
pub const SIDE_BY_SIDE_SPP: u32 = 16;
/// Threads of the side-by-side comparison's main row (the machine's two cores).
pub const SIDE_BY_SIDE_THREADS: usize = 2;
/// Mitsuba 3 variants tried in order: `llvm_ad_rgb` is Mitsuba's fast CPU path (Dr.Jit compiles the
/// whole path tracer with LLVM and runs it over SIMD lanes); `scalar_rgb` is the fallback where the
/// JIT is missing or crashes (with libLLVM 15, Dr.Jit 1.5's kernels hit an LLVM "Cannot select"
/// error on `fminimum`, which LLVM 15 cannot lower on x86; libLLVM 19 works).
pub const MITSUBA_VARIANTS: [&str; 2] = ["llvm_ad_rgb", "scalar_rgb"];
/// The script that renders the exported scene with Mitsuba 3 (shipped in the binary and written
/// into a temporary folder at each run, so `woven bench` runs from any directory).
pub const MITSUBA_SCRIPT: &str = include_str!("../datagen/mitsuba/bench_render.py");
/// Exit code of [`MITSUBA_SCRIPT`] when Mitsuba 3 cannot be imported or lacks the variant.
const MITSUBA_ABSENT_EXIT: i32 = 3;

/// How `woven bench` reaches Mitsuba 3 for its side-by-side timing (issue 16 deliverable 4).
#[derive(Clone, Debug, Default)]
pub struct MitsubaBench {
    /// Python interpreter that can `import mitsuba`; `None` skips the comparison with a note.
    pub python: Option<PathBuf>,
    /// The `woven` executable, to time the whole `woven render` process as Mitsuba's whole
    /// process is timed (start-up included); `None` reports woven's in-process time only.
    pub woven_exe: Option<PathBuf>,
}

/// Woven's figures the comparison reuses from the time-vs-error table.
struct WovenSide {
    /// `(spp, threads)` → (best wall time s, its CPU s, RMSE vs woven's reference, PSNR dB).
    rows: BTreeMap<(u32, usize), (f64, f64, f32, f32)>,
    /// Mean pixel value of woven's reference (scale of its RMSE).
    reference_mean: f32,
    /// Samples per pixel of woven's reference.
    ref_spp: u32,
    /// Repetitions per timing (best kept).
    reps: usize,
}

/// Mean over pixels and channels.
fn mean_value(img: &Image) -> f32 {
    let m = img.mean();
    (m[0] + m[1] + m[2]) / 3.0
}

/// The bench scene as a parameter file: the twill 2/2 preset, the default rig, orthographic,
/// [`BENCH_SIZE`]², `spp` samples. `woven export` of it is what Mitsuba renders side by side.
pub fn bench_params(spp: u32) -> Result<ParamFile> {
    Ok(ParamFile {
        cloth: ClothParams::preset("twill22")?,
        scene: bench_scene(BENCH_SIZE, spp, LightRig::default_rig()),
    })
}

/// What one run of the Mitsuba script gave (`None` in `json`: it failed, `note` says why).
struct ScriptRun {
    wall_s: f64,
    /// CPU seconds of the child process (NaN without `/proc`).
    child_cpu_s: f64,
    json: Option<serde_json::Value>,
    note: String,
    absent: bool,
}

fn run_script(python: &Path, script: &Path, args: &[String]) -> ScriptRun {
    let c0 = cpu_seconds();
    let t0 = Instant::now();
    let out = Command::new(python).arg(script).args(args).output();
    let wall_s = t0.elapsed().as_secs_f64();
    let child_cpu_s = child_cpu_since(c0);
    match out {
        Err(e) => ScriptRun {
            wall_s,
            child_cpu_s,
            json: None,
            note: format!("cannot run the Python interpreter `{}` ({e})", python.display()),
            absent: true,
        },
        Ok(o) if o.status.success() => {
            let stdout = String::from_utf8_lossy(&o.stdout);
            match serde_json::from_str::<serde_json::Value>(stdout.lines().last().unwrap_or("")) {
                Ok(v) => ScriptRun { wall_s, child_cpu_s, json: Some(v), note: String::new(), absent: false },
                Err(e) => ScriptRun {
                    wall_s,
                    child_cpu_s,
                    json: None,
                    note: format!("the Mitsuba script's output is not JSON ({e})"),
                    absent: false,
                },
            }
        }
        Ok(o) => {
            let err = String::from_utf8_lossy(&o.stderr);
            // The last lines say why (an LLVM crash prints hundreds of lines of its DAG before them).
            let tail: Vec<&str> = err.lines().filter(|l| !l.trim().is_empty()).collect();
            let first = tail.iter().find(|l| l.contains("ERROR") || l.contains("Error")).copied();
            let last = tail.last().copied().unwrap_or("no message");
            let why = match first {
                Some(f) if f != last => format!("{} … {}", f.trim(), last.trim()),
                _ => last.trim().to_string(),
            };
            let code = o.status.code();
            ScriptRun {
                wall_s,
                child_cpu_s,
                json: None,
                note: format!(
                    "exit {}: {}",
                    code.map_or("by a signal".to_string(), |c| c.to_string()),
                    why.chars().take(300).collect::<String>()
                ),
                absent: code == Some(MITSUBA_ABSENT_EXIT),
            }
        }
    }
}

/// CPU seconds of the children waited for since `before` (a [`cpu_seconds`] reading).
fn child_cpu_since(before: Option<(f64, f64)>) -> f64 {
    match (before, cpu_seconds()) {
        (Some(a), Some(b)) => b.1 - a.1,
        _ => f64::NAN,
    }
}

fn json_f64(v: &serde_json::Value, key: &str) -> f64 {
    v[key].as_f64().unwrap_or(f64::NAN)
}

/// The side-by-side section: woven and Mitsuba 3 render the same exported geometry (twill 2/2,
/// default rig, orthographic, 256²) at equal spp and threads; each renderer's error is measured
/// against its own high-spp reference (the materials differ: Mitsuba gets the export's stand-in
/// material, so noise levels are compared, not images). Mitsuba being absent, or every variant
/// failing, gives a note in the section, not an error; a failure of woven's own export is an error.
fn mitsuba_side_by_side(cfg: &MitsubaBench, woven: &WovenSide, progress: &dyn Progress) -> Result<String> {
    let mut md = String::from("\n### Side by side with Mitsuba 3\n\n");
    let Some(python) = &cfg.python else {
        md.push_str("Skipped: no Python interpreter given (`--mitsuba-python PATH` or `WOVEN_MITSUBA_PYTHON`).\n");
        return Ok(md);
    };
    // A folder of its own, removed when dropped: two side-by-side runs in one process (the tests
    // run in parallel) must not share it.
    let dir = tempfile::Builder::new().prefix("woven-bench-mitsuba-").tempdir().context("creating a scratch folder")?;
    md.push_str(&side_by_side_in(cfg, python, dir.path(), woven, progress)?);
    Ok(md)
}

fn side_by_side_in(
    cfg: &MitsubaBench,
    python: &Path,
    dir: &Path,
    woven: &WovenSide,
    progress: &dyn Progress,
) -> Result<String> {
    let (spp, threads) = (SIDE_BY_SIDE_SPP, SIDE_BY_SIDE_THREADS);
    let spps = [4u32, spp, 64];
    let mut md = String::new();
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let params = bench_params(spp)?;
    let scene_dir = dir.join("scene");
    export(&params, &scene_dir, &ExportOptions::default()).context("exporting the bench scene")?;
    let params_path = dir.join("params.json");
    let json = serde_json::to_string_pretty(&params).context("serialising the bench scene")?;
    crate::io::write_atomic(&params_path, json.as_bytes()).context("writing the bench scene's parameters")?;
    let script = dir.join("bench_render.py");
    crate::io::write_atomic(&script, MITSUBA_SCRIPT.as_bytes()).context("writing the Mitsuba script")?;
    let xml = scene_dir.join("scene.xml").display().to_string();
    let (ref_spp, reps) = (woven.ref_spp, woven.reps);
    let script_args = |variant: &str, out: &str, threads: usize, spps: &[u32], reps: usize, ref_spp: u32| {
        let mut a: Vec<String> = vec![xml.clone(), "--out-dir".into(), dir.join(out).display().to_string()];
        a.extend(
            ["--variant", variant, "--threads", &threads.to_string(), "--reps", &reps.to_string()].map(String::from),
        );
        for s in spps {
            a.extend(["--spp".to_string(), s.to_string()]);
        }
        a.extend(["--ref-spp".to_string(), ref_spp.to_string()]);
        a
    };

    // The statistics run: the spp of woven's table at 2 threads, then the reference. The first
    // variant that renders is kept.
    let mut tried = Vec::new();
    let mut stats = None;
    for variant in MITSUBA_VARIANTS {
        progress.message(&format!("Mitsuba 3 ({variant}) at {spps:?} spp and {ref_spp} spp …"));
        let r = run_script(python, &script, &script_args(variant, variant, threads, &spps, reps, ref_spp));
        if let Some(v) = r.json {
            stats = Some((variant, v));
            break;
        }
        if r.absent {
            // No interpreter, no Mitsuba, or not this variant: a note, not an error.
            tried.push(r.note);
            break;
        }
        tried.push(format!("`{variant}` failed ({})", r.note));
    }
    let Some((variant, stats)) = stats else {
        writeln!(
            md,
            "Skipped: Mitsuba 3 did not render with `{}`: {}. Install it in a throw-away virtual environment \
             (`python3 -m venv VENV && VENV/bin/pip install mitsuba numpy`) and pass `--mitsuba-python VENV/bin/python`.",
            python.display(),
            tried.join("; ")
        )?;
        return Ok(md);
    };
    // Mitsuba's errors against its own reference, computed with woven's image code.
    let load = |p: &serde_json::Value| -> Result<Image> {
        let path = p.as_str().context("the Mitsuba script named no image")?;
        Image::load(Path::new(path), 1).with_context(|| format!("reading Mitsuba's image {path}"))
    };
    let m_ref = load(&stats["reference"]["exr"])?;
    let m_mean = mean_value(&m_ref);
    // spp → (best wall s, its CPU s, first wall s, RMSE, PSNR).
    let mut m_rows = BTreeMap::new();
    for r in stats["renders"].as_array().map(Vec::as_slice).unwrap_or(&[]) {
        let img = load(&r["exr"])?;
        ensure_same_size(&img, &m_ref)?;
        let s = r["spp"].as_u64().unwrap_or(0) as u32;
        let row = (json_f64(r, "best_s"), json_f64(r, "best_cpu_s"), json_f64(r, "first_s"));
        m_rows.insert(s, (row.0, row.1, row.2, img.rmse(&m_ref), img.psnr_srgb(&m_ref)));
    }
    // One thread, at the comparison's spp (render only).
    progress.message(&format!("Mitsuba 3 ({variant}), 1 thread, {spp} spp …"));
    let one = run_script(python, &script, &script_args(variant, "t1", 1, &[spp], reps, 0));
    let m_one =
        one.json.as_ref().map(|v| (json_f64(&v["renders"][0], "best_s"), json_f64(&v["renders"][0], "best_cpu_s")));

    // Whole processes, start-up included: Mitsuba's script (Python start-up, import, scene load,
    // one render, EXR written) against `woven render` (parameters read, geometry and BVH built,
    // one render, PNG written), each the best of `reps` runs at `threads` threads; CPU seconds
    // are the child's (its user + system time, read when it was waited for).
    progress.message("whole processes …");
    let mut m_whole = (f64::INFINITY, f64::NAN);
    for _ in 0..reps {
        let r = run_script(python, &script, &script_args(variant, "whole", threads, &[spp], 1, 0));
        if r.json.is_some() && r.wall_s < m_whole.0 {
            m_whole = (r.wall_s, r.child_cpu_s);
        }
    }
    let mut w_whole = None;
    if let Some(exe) = &cfg.woven_exe {
        let mut best = (f64::INFINITY, f64::NAN);
        for _ in 0..reps {
            let c0 = cpu_seconds();
            let t0 = Instant::now();
            let st = Command::new(exe)
                .args(["render", "--params"])
                .arg(&params_path)
                .arg("--out")
                .arg(dir.join("woven.png"))
                .args(["--threads", &threads.to_string()])
                .output()
                .with_context(|| format!("running {}", exe.display()))?;
            let t = t0.elapsed().as_secs_f64();
            anyhow::ensure!(
                st.status.success(),
                "`woven render` of the bench scene failed: {}",
                String::from_utf8_lossy(&st.stderr).trim()
            );
            if t < best.0 {
                best = (t, child_cpu_since(c0));
            }
        }
        w_whole = Some(best);
    }

    let fmt = |t: f64, digits: usize| if t.is_finite() { format!("{t:.digits$}") } else { "—".to_string() };
    writeln!(
        md,
        "Both renderers draw the same geometry: `woven export` of the bench scene (the twill's exact centre curves as \
         Mitsuba `bsplinecurve`s, the same orthographic view, {BENCH_SIZE}×{BENCH_SIZE} pixels, the same five lights \
         scaled by the exposure), rendered by Mitsuba {} `{variant}` through `datagen/mitsuba/bench_render.py` \
         (Python {}; the script ships in the binary). The materials differ (Mitsuba gets the export's stand-in: \
         diffuse + GGX blended with a rough dielectric, path depth 16; woven its BYSDF, up to 4 vertices), so the \
         images are not compared with each other: each renderer's error is against its own {ref_spp}-spp reference, \
         and the relative RMSE (RMSE / the reference's mean pixel value) compares noise levels. Render-only times \
         are the best of {reps}; Mitsuba's include reading the image back (Dr.Jit evaluates lazily) and its first \
         render (JIT compilation or kernel-cache load) is shown apart; CPU seconds are user + system over all \
         threads of the render.\n",
        stats["mitsuba"].as_str().unwrap_or("?"),
        stats["python"].as_str().unwrap_or("?"),
    )?;
    writeln!(md, "| renderer | spp | threads | render only, wall (s) | CPU (s) | first render (s) | RMSE vs own reference | relative RMSE | PSNR (sRGB, dB) |\n|---|---|---|---|---|---|---|---|---|")?;
    for s in spps {
        if let Some(&(t, c, e, p)) = woven.rows.get(&(s, threads)) {
            writeln!(
                md,
                "| woven | {s} | {threads} | {t:.3} | {} | — | {e:.4} | {:.3} | {p:.1} |",
                fmt(c, 2),
                e / woven.reference_mean
            )?;
        }
        if let Some(&(t, c, t1, e, p)) = m_rows.get(&s) {
            writeln!(
                md,
                "| Mitsuba `{variant}` | {s} | {threads} | {t:.3} | {} | {} | {e:.4} | {:.3} | {p:.1} |",
                fmt(c, 2),
                fmt(t1, 3),
                e / m_mean
            )?;
        }
    }
    if let Some(&(t, c, e, p)) = woven.rows.get(&(spp, 1)) {
        writeln!(
            md,
            "| woven | {spp} | 1 | {t:.3} | {} | — | {e:.4} | {:.3} | {p:.1} |",
            fmt(c, 2),
            e / woven.reference_mean
        )?;
    }
    if let Some((t, c)) = m_one {
        writeln!(md, "| Mitsuba `{variant}` | {spp} | 1 | {} | {} | — | as at 2 threads | | |", fmt(t, 3), fmt(c, 2))?;
    }

    let ratio = |a: f64, b: f64| {
        if a.is_finite() && b.is_finite() && b > 0.0 {
            format!("**{:.2}×**", a / b)
        } else {
            "—".into()
        }
    };
    let w2 = woven.rows.get(&(spp, threads)).map_or((f64::NAN, f64::NAN), |r| (r.0, r.1));
    let m2 = m_rows.get(&spp).map_or((f64::NAN, f64::NAN), |r| (r.0, r.1));
    writeln!(md, "\n| at {spp} spp, {threads} threads | woven wall (s) | Mitsuba `{variant}` wall (s) | woven / Mitsuba, wall | woven CPU (s) | Mitsuba CPU (s) | woven / Mitsuba, CPU |\n|---|---|---|---|---|---|---|")?;
    // One row of the ratio table: woven's and Mitsuba's (wall, CPU) seconds and their ratios.
    let ratio_row = |md: &mut String, label: &str, w: (f64, f64), m: (f64, f64)| {
        writeln!(
            md,
            "| {label} | {} | {} | {} | {} | {} | {} |",
            fmt(w.0, 3),
            fmt(m.0, 3),
            ratio(w.0, m.0),
            fmt(w.1, 2),
            fmt(m.1, 2),
            ratio(w.1, m.1)
        )
    };
    ratio_row(&mut md, "render only", w2, m2)?;
    let ww = w_whole.unwrap_or((f64::NAN, f64::NAN));
    ratio_row(&mut md, "whole process (start-up, scene load, render, image written)", ww, m_whole)?;
    // Equal noise, measured: the fewest spp of woven's table whose relative RMSE is at most
    // Mitsuba's at the comparison's spp (no extrapolation by the 1/√spp law).
    if let Some(&(tm, cm, _, em, _)) = m_rows.get(&spp) {
        let target = em / m_mean;
        let hit = woven
            .rows
            .iter()
            .filter(|((_, th), r)| *th == threads && r.2 / woven.reference_mean <= target)
            .min_by_key(|((s, _), _)| *s);
        match hit {
            Some(((s, _), &(tw, cw, ew, _))) => {
                let label = format!(
                    "render only at equal noise: woven at {s} spp (relative RMSE {:.3}) against Mitsuba at {spp} spp ({target:.3})",
                    ew / woven.reference_mean
                );
                ratio_row(&mut md, &label, (tw, cw), (tm, cm))?
            }
            None => writeln!(
                md,
                "| render only at equal noise | — (no spp of woven's table reaches Mitsuba's relative RMSE {target:.3}) | {tm:.3} | — | | | |"
            )?,
        }
    }
    writeln!(md, "\nA ratio above 1 means woven is slower.")?;
    if !tried.is_empty() {
        writeln!(md, "Variants tried before `{variant}`: {}.", tried.join("; "))?;
    }
    if one.json.is_none() {
        writeln!(md, "The one-thread Mitsuba run failed: {}.", one.note)?;
    }
    Ok(md)
}

fn ensure_same_size(a: &Image, b: &Image) -> Result<()> {
    anyhow::ensure!(
        (a.width, a.height) == (b.width, b.height),
        "Mitsuba's images differ in size ({}×{} vs {}×{})",
        a.width,
        a.height,
        b.width,
        b.height
    );
    Ok(())
}

/// Run the benchmark and return its markdown section (the `woven bench` command prints it and
/// writes it into `docs/benchmarks.md` with [`replace_section`]). Each measurement is announced
/// to `progress` as a message.
pub fn run(quick: bool, mitsuba: &MitsubaBench, progress: &dyn Progress) -> Result<String> {
    let cloth = ClothParams::preset("twill22")?;
    let size = BENCH_SIZE;
    let ref_spp = if quick { 256 } else { 1024 };
    let reps = if quick { 1 } else { 3 };
    let mut md = String::new();
    let cmd = if quick { "woven bench --quick" } else { "woven bench" };
    writeln!(md, "Command: `{cmd}` (release build). Scene: twill 2/2, default light rig (ambient + front, back, two sides), orthographic, 2 repeats across, {size}×{size}. Best of {reps} runs.\n")?;
    let load = load_average().map_or("unknown".to_string(), |l| format!("{l:.1}"));
    writeln!(md, "Load average (1 min) at the start: {load} on this machine's cores; wall times grow with it, CPU seconds (user + system, `/proc/self/stat`) do not.\n")?;
    progress.message(&format!("reference render at {ref_spp} spp …"));
    let (t_ref, reference) =
        time(1, || render(&cloth, &bench_scene(size, ref_spp, LightRig::default_rig()), &RenderOptions::default()));
    writeln!(md, "Reference: {ref_spp} spp, {t_ref:.1} s on 2 threads.\n")?;
    writeln!(md, "### Time vs error\n\n| spp | threads | wall time (s) | CPU time (s) | RMSE vs reference (linear) | PSNR (sRGB, dB) |\n|---|---|---|---|---|---|")?;
    // (spp, threads) -> (time, RMSE, PSNR): the woven side of the Mitsuba comparison below.
    let mut woven_rows = BTreeMap::new();
    for spp in [1u32, 4, 16, 64] {
        for threads in [1usize, 2] {
            let scene = bench_scene(size, spp, LightRig::default_rig());
            let opts = RenderOptions { threads: Some(threads), ..Default::default() };
            let (t, cpu, img) = time_cpu(reps, || render(&cloth, &scene, &opts));
            woven_rows.insert((spp, threads), (t, cpu, img.rmse(&reference), img.psnr_srgb(&reference)));
            writeln!(
                md,
                "| {spp} | {threads} | {t:.3} | {cpu:.2} | {:.4} | {:.1} |",
                img.rmse(&reference),
                img.psnr_srgb(&reference)
            )?;
            progress.message(&format!("{spp} spp, {threads} threads: {t:.3} s"));
        }
    }
    let woven_side = WovenSide { rows: woven_rows, reference_mean: mean_value(&reference), ref_spp, reps };
    md.push_str(&mitsuba_side_by_side(mitsuba, &woven_side, progress)?);
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::progress::NoProgress;

    #[test]
    fn cpu_time_is_read_past_a_command_name_with_spaces_and_parentheses() {
        // pid (comm) state ppid pgrp session tty tpgid flags minflt cminflt majflt cmajflt utime stime cutime cstime …
        let stat = "4242 (wov en) (x)) R 1 2 3 4 5 6 7 8 9 10 250 75 30 20 20 0 3 0";
        assert_eq!(cpu_seconds_of_stat(stat), Some((3.25, 0.5)));
        assert_eq!(cpu_seconds_of_stat("4242 (woven) R 1 2"), None);
        assert_eq!(cpu_seconds_of_stat("4242 (woven) R 1 2 3 4 5 6 7 8 9 10 x 75 0 0"), None);
        assert_eq!(cpu_seconds_of_stat("no parenthesis"), None);
    }

    fn woven_side() -> WovenSide {
        let mut rows = BTreeMap::new();
        rows.insert((SIDE_BY_SIDE_SPP, SIDE_BY_SIDE_THREADS), (1.0, 2.0, 0.01, 30.0));
        WovenSide { rows, reference_mean: 0.2, ref_spp: 8, reps: 1 }
    }

    /// Issue 16 deliverable 4: without Mitsuba the bench's section says so and the bench goes on.
    #[test]
    fn a_missing_mitsuba_gives_a_note_not_an_error() {
        let bogus = MitsubaBench { python: Some("/nonexistent/woven-test/python3".into()), woven_exe: None };
        let md = mitsuba_side_by_side(&bogus, &woven_side(), &NoProgress).expect("a note, not an error");
        assert!(md.contains("### Side by side with Mitsuba 3"), "{md}");
        assert!(md.contains("Skipped") && md.contains("cannot run the Python interpreter"), "{md}");
        assert!(md.contains("/nonexistent/woven-test/python3"), "{md}");
        let none = MitsubaBench::default();
        let md = mitsuba_side_by_side(&none, &woven_side(), &NoProgress).unwrap();
        assert!(md.contains("Skipped: no Python interpreter"), "{md}");
    }

    /// An interpreter that runs but cannot import Mitsuba (the script's exit code 3), and one on
    /// which every variant crashes (an LLVM abort), both end in a note naming the cause.
    #[cfg(unix)]
    #[test]
    fn a_python_without_mitsuba_or_a_crashing_one_gives_a_note() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        let fake = |name: &str, body: &str| {
            let p = dir.path().join(name);
            std::fs::write(&p, format!("#!/bin/sh\n{body}\n")).unwrap();
            std::fs::set_permissions(&p, std::fs::Permissions::from_mode(0o755)).unwrap();
            p
        };
        let no_module = fake("py-absent", "echo \"No module named 'mitsuba'\" >&2; exit 3");
        let cfg = MitsubaBench { python: Some(no_module), woven_exe: None };
        let md = mitsuba_side_by_side(&cfg, &woven_side(), &NoProgress).unwrap();
        assert!(md.contains("Skipped") && md.contains("No module named 'mitsuba'"), "{md}");
        let crash = fake("py-crash", "echo 'LLVM ERROR: Cannot select' >&2; exit 134");
        let cfg = MitsubaBench { python: Some(crash), woven_exe: None };
        let md = mitsuba_side_by_side(&cfg, &woven_side(), &NoProgress).unwrap();
        for v in MITSUBA_VARIANTS {
            assert!(md.contains(&format!("`{v}` failed (exit 134: LLVM ERROR: Cannot select)")), "{md}");
        }
    }

    /// The scene Mitsuba renders is the bench's: orthographic, the bench's size and spp, the
    /// default rig's four lights plus the ambient, the twill's round yarns as B-spline curves,
    /// and the orthographic width of the renderer's view (2 repeats across).
    #[test]
    fn the_exported_bench_scene_is_the_bench_view() {
        let dir = tempfile::tempdir().unwrap();
        let params = bench_params(SIDE_BY_SIDE_SPP).unwrap();
        let s = export(&params, dir.path(), &ExportOptions::default()).unwrap();
        let xml = std::fs::read_to_string(dir.path().join("scene.xml")).unwrap();
        assert!(xml.contains("<sensor type=\"orthographic\">"));
        assert!(xml.contains(&format!("<integer name=\"width\" value=\"{BENCH_SIZE}\"/>")));
        assert!(xml.contains(&format!("<integer name=\"height\" value=\"{BENCH_SIZE}\"/>")));
        assert!(xml.contains(&format!("<integer name=\"sample_count\" value=\"{SIDE_BY_SIDE_SPP}\"/>")));
        assert_eq!(xml.matches("<emitter ").count(), LightRig::default_rig().lights.len() + 1);
        assert_eq!(xml.matches("<shape type=\"bsplinecurve\">").count(), 2);
        let scale = xml.split("<scale x=\"").nth(1).unwrap();
        let half_w: f32 = scale[..scale.find('"').unwrap()].parse().unwrap();
        let across = params.scene.camera.tiles * s.tile_size[0];
        assert!((half_w - 0.5 * across).abs() < 1e-3 * across, "half width {half_w}, view {across}");
    }
}
