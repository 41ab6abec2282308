#!/usr/bin/env python3
"""Run the fit on every render of one or more Mitsuba test-set folders (the user's path, no flags).

For each `NAME.png` listed in `DIR/index.json` this runs

    nice WOVEN fit DIR/NAME.png --out OUT/NAME

under `timeout` (default 360 s wall clock) and optionally a CPU-time limit (`--cpu-limit`), and writes
`OUT/NAME/run.json` with the command, exit status, wall and CPU time, the load average and the last lines of
the fit's output. A folder whose `run.json` already exists is skipped, so an interrupted
run resumes; `--retry-timed-out` runs the timed-out ones again (keeping the earlier record as `run.N.json`).
Only the Python standard library is needed.
"""
import argparse
import json
import os
import resource
import subprocess
import sys
import time


def atomic_write_json(path, obj):
    """Write `obj` as JSON to `path` through a temporary file + rename (no half-written file)."""
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(obj, f, indent=1)
    os.replace(tmp, path)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dirs", nargs="+", help="test-set folders holding index.json and NAME.png")
    ap.add_argument("--woven", required=True, help="the woven binary to run")
    ap.add_argument("--out", required=True, help="output folder; one sub-folder per image")
    ap.add_argument("--timeout", type=int, default=360,
                    help="wall-clock seconds before a fit is stopped (default 360)")
    ap.add_argument("--cpu-limit", type=int, default=0,
                    help="CPU seconds (all threads) before a fit is stopped, 0 = none (default 0). On a machine "
                         "whose cores are shared, a CPU-time limit stops the same work whatever the load: 720 "
                         "CPU s is 6 minutes of two busy cores")
    ap.add_argument("--prep-stopped", action="store_true",
                    help="instead of fitting, run `WOVEN prep IMG --out OUT/NAME/prep` for every image whose fit "
                         "ended without a result (to see which grid and angle the fit would have started from)")
    ap.add_argument("--retry-timed-out", action="store_true",
                    help="run again the images whose last run timed out (their run.json is kept as "
                         "run.N.json); for runs stopped only because other work shared the cores")
    args = ap.parse_args()
    if not os.access(args.woven, os.X_OK):
        sys.exit(f"error: {args.woven} is not an executable file")
    os.makedirs(args.out, exist_ok=True)
    for d in args.dirs:
        index_path = os.path.join(d, "index.json")
        try:
            with open(index_path) as f:
                index = json.load(f)
        except (OSError, json.JSONDecodeError) as e:
            sys.exit(f"error: cannot read {index_path}: {e}")
        for entry in index:
            name = entry["name"]
            img = os.path.join(d, name + ".png")
            out = os.path.join(args.out, name)
            run_json = os.path.join(out, "run.json")
            if args.prep_stopped:
                if not os.path.exists(run_json):
                    continue
                with open(run_json) as f:
                    if json.load(f)["exit_code"] == 0:
                        continue
                prep_out = os.path.join(out, "prep")
                p = subprocess.run(["nice", args.woven, "prep", img, "--out", prep_out], capture_output=True,
                                   text=True)
                print(f"{name}: prep exit {p.returncode}: {(p.stdout + p.stderr).strip()[-300:]}", flush=True)
                continue
            if os.path.exists(run_json):
                with open(run_json) as f:
                    previous = json.load(f)
                if not (args.retry_timed_out and (previous.get("timed_out") or previous.get("cpu_limited"))):
                    print(f"{name}: done already, skipped", flush=True)
                    continue
                attempt = 1
                while os.path.exists(os.path.join(out, f"run.{attempt}.json")):
                    attempt += 1
                os.replace(run_json, os.path.join(out, f"run.{attempt}.json"))
            if not os.path.exists(img):
                sys.exit(f"error: {img} listed in {index_path} does not exist")
            cmd = ["nice", args.woven, "fit", img, "--out", out]
            limit = None
            if args.cpu_limit > 0:
                # RLIMIT_CPU is inherited through `timeout` and `nice` (exec); the soft limit sends SIGXCPU,
                # which ends the fit (exit 128 + 24 through `timeout`), the hard one SIGKILL 5 s later.
                def limit():
                    resource.setrlimit(resource.RLIMIT_CPU, (args.cpu_limit, args.cpu_limit + 5))
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            t0 = time.monotonic()
            p = subprocess.run(["timeout", str(args.timeout)] + cmd, capture_output=True, text=True,
                               preexec_fn=limit)
            wall = time.monotonic() - t0
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
            load = os.getloadavg()[0]
            tail = (p.stdout + p.stderr).splitlines()[-30:]
            os.makedirs(out, exist_ok=True)
            with open(os.path.join(out, "stdout.log"), "w") as f:
                f.write(p.stdout)
                f.write(p.stderr)
            atomic_write_json(run_json, {
                "name": name,
                "source_dir": os.path.abspath(d),
                "command": " ".join(cmd),
                "timeout_s": args.timeout,
                "cpu_limit_s": args.cpu_limit,
                "exit_code": p.returncode,
                "timed_out": p.returncode in (124, 137),
                "cpu_limited": p.returncode in (128 + 24, -24, 128 + 9, -9) and args.cpu_limit > 0,
                "wall_s": wall,
                "cpu_s": cpu,
                "load_avg_1min_at_end": load,
                "output_tail": tail,
            })
            print(f"{name}: exit {p.returncode} in {wall:.1f} s wall, {cpu:.1f} s CPU", flush=True)


if __name__ == "__main__":
    main()
