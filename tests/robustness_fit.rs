//! Bad input to `woven fit` (issue 12, deliverable 7): images that hold no linear picture of cloth,
//! out-of-range flags, an output folder that cannot be written, and Ctrl-C. Each case fails before
//! the fit starts with a clear message and a non-zero exit (never a panic, a hang, or minutes of
//! fitting thrown away at the end), and an interrupted fit never damages an earlier complete one.
//! Each test also runs the good neighbour of its bad input, so it can fail.

use std::ffi::OsStr;
use std::fmt::Debug;
use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};
use woven::image_io::Image;

/// Wait for `child` for at most `limit`; a run past it is killed and fails the test (a hang).
fn wait_limited(mut child: Child, limit: Duration, what: &str) -> Output {
    let start = Instant::now();
    while child.try_wait().expect("wait").is_none() {
        if start.elapsed() > limit {
            child.kill().ok();
            child.wait().ok();
            panic!("{what} did not finish within {} s", limit.as_secs());
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let mut out = Vec::new();
    let mut err = Vec::new();
    if let Some(mut o) = child.stdout.take() {
        o.read_to_end(&mut out).ok();
    }
    if let Some(mut e) = child.stderr.take() {
        e.read_to_end(&mut err).ok();
    }
    Output { status: child.wait().expect("status"), stdout: out, stderr: err }
}

fn spawn<S: AsRef<OsStr>>(args: &[S]) -> Child {
    Command::new(env!("CARGO_BIN_EXE_woven"))
        .args(args)
        .env("RUST_BACKTRACE", "0")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("run woven")
}

/// Run `woven args`; it must end within `limit`.
fn woven<S: AsRef<OsStr> + Debug>(args: &[S], limit: Duration) -> Output {
    wait_limited(spawn(args), limit, &format!("woven {args:?}"))
}

/// Stderr of a run that must fail cleanly within `limit`.
fn fails_within<S: AsRef<OsStr> + Debug>(args: &[S], limit: Duration) -> String {
    let out = woven(args, limit);
    let err = String::from_utf8_lossy(&out.stderr).to_string();
    assert!(!out.status.success(), "woven {args:?} should fail; stderr: {err}");
    assert!(!err.contains("panicked"), "woven {args:?}: {err}");
    err
}

/// Stderr of a run that must succeed.
fn succeeds(args: &[&str]) -> String {
    let out = woven(args, Duration::from_secs(300));
    let err = String::from_utf8_lossy(&out.stderr).to_string();
    assert!(out.status.success(), "woven {args:?}: {err}");
    err
}

fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

/// A linear EXR of one repeat of a plain weave (32×32 px), the fit's input in these tests.
fn plain_exr(dir: &Path) -> PathBuf {
    let out = woven(&["params", "--preset", "plain"], Duration::from_secs(60));
    assert!(out.status.success());
    let pf = dir.join("plain.json");
    std::fs::write(&pf, out.stdout).unwrap();
    let (png, exr) = (dir.join("plain.png"), dir.join("plain.exr"));
    let size = ["--width", "32", "--height", "32", "--tiles", "1", "--spp", "4"];
    succeeds(&[&["render", "--params", s(&pf), "--out", s(&png), "--exr", s(&exr)][..], &size].concat());
    exr
}

/// Fit settings that keep a complete run to seconds: no preparation or pre-estimation, the
/// pattern given, small renders; then `iterations`.
fn quick(iterations: &'static str) -> Vec<&'static str> {
    vec![
        "--no-prep",
        "--no-pre-estimate",
        "--pattern",
        "plain",
        "--fast",
        "--px-per-cell",
        "8",
        "--iterations",
        iterations,
    ]
}

/// A fit that would take hours: a check that must come before the fit fails fast only if it does.
fn endless() -> Vec<&'static str> {
    // Without `--fast`, which caps the iterations at the default (100 then, 30 since session 22):
    // on an idle machine with the session-15 renderer that cap ended the "endless" joint loop in
    // about a second, before the test's Ctrl-C arrived.
    quick("10000000").into_iter().filter(|a| *a != "--fast").collect()
}

/// `woven fit INPUT --out OUT` with the endless settings and `extra`.
fn endless_fit<'a>(input: &'a Path, out: &'a Path, extra: &[&'a str]) -> Vec<&'a str> {
    [&["fit", s(input), "--out", s(out)][..], &endless(), extra].concat()
}

/// Refusals must come before the fit starts: well within this.
const EARLY: Duration = Duration::from_secs(30);

/// An `--out` below a regular file: it cannot be created, and `woven fit` must say so before it
/// fits (the fit below would run for hours).
fn blocked_out(dir: &Path) -> PathBuf {
    let blocker = dir.join("blocker");
    std::fs::write(&blocker, b"x").unwrap();
    blocker.join("out")
}

/// Names in `dir` (sorted).
fn names(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> =
        std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    v.sort();
    v
}

#[test]
fn an_exr_without_a_linear_picture_is_refused_before_fitting() {
    let d = tempfile::tempdir().unwrap();
    let exr = plain_exr(d.path());
    let img = Image::load(&exr, 16).unwrap();
    let scaled = |k: f32, name: &str| {
        let p = d.path().join(name);
        let data = img.data.iter().map(|px| px.map(|c| c * k)).collect();
        Image::new(img.width, img.height, data).save_exr(&p).unwrap();
        p
    };
    let (negative, huge) = (scaled(-1.0, "negative.exr"), scaled(1e30, "huge.exr"));
    let out = d.path().join("out");
    let fit = |input, out| endless_fit(input, out, &[]);
    let e = fails_within(&fit(&negative, &out), EARLY);
    assert!(e.contains("negative.exr") && e.contains("no positive value"), "{e}");
    let e = fails_within(&fit(&huge, &out), EARLY);
    assert!(e.contains("huge.exr") && e.contains("is this a linear image? rescale it"), "{e}");
    assert!(!out.exists(), "nothing is written for a refused input");
    assert_eq!(names(d.path()), ["huge.exr", "negative.exr", "plain.exr", "plain.json", "plain.png"]);
    // The good neighbour passes the input checks and reaches the output check (which refuses it
    // here, so that the test does not run the fit).
    let e = fails_within(&fit(&exr, &blocked_out(d.path())), EARLY);
    assert!(e.contains("--out") && e.contains("cannot create its parent folder"), "{e}");
}

#[test]
fn out_of_range_flags_are_refused_with_a_hint() {
    let d = tempfile::tempdir().unwrap();
    let exr = plain_exr(d.path());
    let out = d.path().join("out");
    let fit = |flag: &str, value: &str| {
        fails_within(&[&["fit", s(&exr), "--out", s(&out)][..], &endless(), &[flag, value]].concat(), EARLY)
    };
    for bad in ["NaN", "inf", "-5", "0"] {
        let e = fit("--energy-scale", bad);
        assert!(e.contains("--energy-scale") && e.contains("finite number > 0"), "{bad}: {e}");
    }
    // `--spp 0` is refused as `woven render` refuses it (it used to be raised to 1 silently).
    let e = fit("--spp", "0");
    let pf = d.path().join("plain.json");
    let r = fails_within(&["render", "--params", s(&pf), "--out", s(&d.path().join("r.png")), "--spp", "0"], EARLY);
    let same = "= 0 is out of range: allowed [1, 65536]";
    assert!(e.contains("--spp") && e.contains(same) && r.contains(same), "fit: {e}\nrender: {r}");
    let e = fit("--seed", "-1");
    assert!(e.contains("seed must be a non-negative integer"), "{e}");
    let e = fit("--threads", "0");
    assert!(e.contains("threads must be a whole number from 1 to"), "{e}");
    let e = fit("--lights", "moon");
    assert!(e.contains("unknown light rig `moon`") && e.contains("known: default, front"), "{e}");
    assert!(!out.exists());
    // Good values parse and reach the output check.
    let good = ["--energy-scale", "2.5", "--spp", "1", "--seed", "3", "--threads", "1", "--lights", "front"];
    let blocked = blocked_out(d.path());
    let e = fails_within(&[&["fit", s(&exr), "--out", s(&blocked)][..], &endless(), &good].concat(), EARLY);
    assert!(e.contains("cannot create its parent folder"), "{e}");
}

#[test]
fn an_unwritable_out_or_model_is_refused_before_fitting() {
    let d = tempfile::tempdir().unwrap();
    let exr = plain_exr(d.path());
    let fit =
        |out: &Path, extra: &[&str]| endless_fit(&exr, out, extra).iter().map(|a| a.to_string()).collect::<Vec<_>>();
    // Below a regular file, a regular file itself, and a path that names no folder.
    let blocked = blocked_out(d.path());
    let e = fails_within(&fit(&blocked, &[]), EARLY);
    assert!(e.contains(s(&blocked)) && e.contains("cannot create its parent folder"), "{e}");
    let e = fails_within(&fit(&d.path().join("plain.png"), &[]), EARLY);
    assert!(e.contains("exists and is not a folder"), "{e}");
    let e = fails_within(&fit(Path::new(".."), &[]), EARLY);
    assert!(e.contains("name a folder"), "{e}");
    // A folder without write permission (root may write anywhere: checked only where it binds).
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        let ro = d.path().join("read-only");
        std::fs::create_dir(&ro).unwrap();
        std::fs::set_permissions(&ro, std::fs::Permissions::from_mode(0o555)).unwrap();
        if std::fs::write(ro.join("probe"), b"x").is_err() {
            let e = fails_within(&fit(&ro.join("out"), &[]), EARLY);
            assert!(e.contains("cannot write in"), "{e}");
        }
        std::fs::set_permissions(&ro, std::fs::Permissions::from_mode(0o755)).unwrap();
    }
    // A model that is not a regular file is refused before the fit, not read (a FIFO would block).
    let fifo = d.path().join("model.fifo");
    if Command::new("mkfifo").arg(&fifo).status().map(|s| s.success()).unwrap_or(false) {
        let e = fails_within(&fit(&d.path().join("out"), &["--model", s(&fifo)]), EARLY);
        assert!(e.contains("--model") && e.contains("not a regular file"), "{e}");
    }
    assert!(!d.path().join("out").exists());
    assert!(names(d.path()).iter().all(|n| !n.contains(".tmp-")), "temporaries left: {:?}", names(d.path()));
}

/// Send SIGINT (Ctrl-C) `times` times to `woven fit` once it says it is fitting, and wait for it.
#[cfg(unix)]
fn interrupted_fit(args: &[&str], times: usize) -> Output {
    let mut child = spawn(args);
    let stderr = child.stderr.take().expect("stderr");
    let (tx, rx) = std::sync::mpsc::channel();
    // Stderr is read on a thread (so the child never blocks on a full pipe) and handed back whole.
    let reader = std::thread::spawn(move || {
        let mut all = String::new();
        let mut told = false;
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            all.push_str(&line);
            all.push('\n');
            // The line is printed once the Ctrl-C handler is in place.
            if !told && line.starts_with("fitting ") {
                tx.send(()).ok();
                told = true;
            }
        }
        all
    });
    rx.recv_timeout(Duration::from_secs(60)).expect("woven fit never started fitting");
    // Let it run into the joint loop before it is stopped.
    std::thread::sleep(Duration::from_millis(1500));
    for _ in 0..times {
        let sent = Command::new("kill").args(["-INT", &child.id().to_string()]).status().expect("kill");
        assert!(sent.success());
        std::thread::sleep(Duration::from_millis(100));
    }
    let mut out = wait_limited(child, Duration::from_secs(120), "the interrupted fit");
    out.stderr = reader.join().expect("stderr reader").into_bytes();
    out
}

#[cfg(unix)]
#[test]
fn ctrl_c_never_replaces_a_complete_fit() {
    let d = tempfile::tempdir().unwrap();
    let exr = plain_exr(d.path());
    let out = d.path().join("out");
    let partial = d.path().join("out.partial");
    let long = [&["fit", s(&exr), "--out", s(&out)][..], &endless()].concat();

    // Stopped with no earlier fit: the best so far goes to OUT.partial; OUT is not created.
    let o = interrupted_fit(&long, 1);
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(o.status.success(), "{err}");
    assert!(err.contains("stopped early") && err.contains("out.partial") && err.contains("was not written"), "{err}");
    assert!(!out.exists() && partial.join("fit.json").is_file());
    woven::ParamFile::load(&partial.join("fit.json")).unwrap();

    // A complete fit replaces whatever OUT held, as a whole, and shows its stages on the way.
    std::fs::create_dir(&out).unwrap();
    std::fs::write(out.join("stale.txt"), b"from an older run").unwrap();
    let err = succeeds(&[&["fit", s(&exr), "--out", s(&out)][..], &quick("6")].concat());
    assert!(err.contains("fitting ") && err.contains("fit: 6/6") && err.contains("writing the outputs"), "{err}");
    assert!(!out.join("stale.txt").exists(), "OUT is replaced whole");
    for f in ["fit.json", "fit.png", "compare.png", "trace.png", "log.jsonl", "stages.json", "export"] {
        assert!(out.join(f).exists(), "{f} missing");
    }
    let log = std::fs::read(out.join("log.jsonl")).unwrap();
    let fit_json = std::fs::read(out.join("fit.json")).unwrap();
    assert_eq!(String::from_utf8_lossy(&log).lines().count(), 6);

    // Stopped with a complete fit in OUT: OUT stays byte for byte; the early stop replaces OUT.partial.
    std::fs::write(partial.join("marker"), b"previous partial").unwrap();
    let o = interrupted_fit(&long, 1);
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(o.status.success(), "{err}");
    assert!(err.contains("stopped early") && err.contains("keeps the earlier complete fit"), "{err}");
    assert_eq!(std::fs::read(out.join("log.jsonl")).unwrap(), log, "log.jsonl of the complete fit changed");
    assert_eq!(std::fs::read(out.join("fit.json")).unwrap(), fit_json);
    assert!(partial.join("fit.json").is_file() && !partial.join("marker").exists());
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains("(stopped early: best so far)") && stdout.contains("out.partial"), "{stdout}");
    // No staging or set-aside folder is left.
    assert_eq!(names(d.path()), ["out", "out.partial", "plain.exr", "plain.json", "plain.png"]);

    // A second Ctrl-C aborts without writing: both folders stay as they were, no temporary is left.
    let partial_json = std::fs::read(partial.join("fit.json")).unwrap();
    let o = interrupted_fit(&long, 2);
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert_eq!(o.status.code(), Some(130), "{err}");
    assert!(err.contains("aborted: nothing written"), "{err}");
    assert_eq!(std::fs::read(out.join("log.jsonl")).unwrap(), log);
    assert_eq!(std::fs::read(partial.join("fit.json")).unwrap(), partial_json);
    assert_eq!(names(d.path()), ["out", "out.partial", "plain.exr", "plain.json", "plain.png"]);
}

#[test]
fn eval_lights_apply_to_a_folder_only() {
    let d = tempfile::tempdir().unwrap();
    // The synthetic targets are rendered under their own rigs: a rig for them is refused.
    let e = fails_within(&["eval", "--count", "1", "--lights", "front"], EARLY);
    assert!(e.contains("--lights applies to --real or --renders"), "{e}");
    // With a folder of renders the rig is taken (the empty folder is what fails then).
    let e = fails_within(&["eval", "--renders", s(d.path()), "--lights", "front"], EARLY);
    assert!(e.contains("holds no NAME.json"), "{e}");
}
