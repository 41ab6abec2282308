#!/usr/bin/env python3
"""Render a `woven export` scene with Mitsuba 3 for `woven bench` (issue 16: the renderer timed side by side).

    python bench_render.py SCENE_XML --out-dir DIR [--variant llvm_ad_rgb] [--threads 2]
                           [--spp 16 [--spp 64 ...]] [--reps 3] [--ref-spp 1024] [--seed 1]

Loads the scene, renders it at each `--spp` (best of `--reps` renders, each with its own seed, the first
one's time reported separately: for `llvm_ad_rgb` it holds the JIT compilation or the kernel-cache load),
optionally at `--ref-spp` as the noise reference, writes every image as a linear-RGB EXR into DIR
(`m_SPP.exr`, `m_ref.exr`) and prints one JSON object on stdout:

    {"mitsuba": "3.9.1", "variant": ..., "threads": N, "import_s": ..., "load_s": ...,
     "renders": [{"spp": 16, "first_s": ..., "best_s": ..., "best_cpu_s": ..., "exr": ...}, ...],
     "reference": {"spp": 1024, "s": ..., "cpu_s": ..., "exr": ...} or null}

Every time is wall clock (`*_s`) or the process's CPU time over all its threads (`*_cpu_s`,
`time.process_time`) around `mi.render` plus the read-back of the image into numpy (Dr.Jit evaluates
lazily: the read-back makes sure the image was computed). `woven bench` computes the errors itself, with
the same code for both renderers' images. Exit codes: 0 done, 3 Mitsuba (or numpy) cannot be imported or
lacks the variant (the caller prints a note and carries on), 2 bad arguments, anything else a failure.
"""

import argparse
import json
import os
import sys
import time

T_START = time.perf_counter()


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", help="scene.xml written by `woven export`")
    ap.add_argument("--out-dir", required=True, help="folder for the EXR images (created)")
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--threads", type=int, default=0, help="worker threads (0: Dr.Jit's default, every core)")
    ap.add_argument("--spp", type=int, action="append", help="samples per pixel (repeatable; default 16)")
    ap.add_argument("--reps", type=int, default=1, help="renders per spp (best time kept)")
    ap.add_argument("--ref-spp", type=int, default=0, help="also render a reference at this spp (0: none)")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    spps = args.spp or [16]
    if any(s < 1 for s in spps) or args.reps < 1 or args.ref_spp < 0 or args.threads < 0:
        ap.error("spp and reps must be positive, ref-spp and threads non-negative")
    if not os.path.isfile(args.scene):
        ap.error(f"no scene file {args.scene!r}")

    t_imp = time.perf_counter()
    try:
        import numpy as np
        import drjit as dr
        import mitsuba as mi
    except ImportError as e:
        print(f"cannot import Mitsuba 3 with this interpreter ({sys.executable}): {e}", file=sys.stderr)
        sys.exit(3)
    if args.variant not in mi.variants():
        print(f"Mitsuba {mi.__version__} lacks the variant {args.variant!r} (has: {', '.join(mi.variants())})",
              file=sys.stderr)
        sys.exit(3)
    mi.set_variant(args.variant)
    import_s = time.perf_counter() - t_imp

    # The scene's curve and mesh files are named relative to the scene file.
    t0 = time.perf_counter()
    scene = mi.load_file(os.path.abspath(args.scene))
    load_s = time.perf_counter() - t0
    # The thread count is set after loading: with a pool of one thread set before, loading the
    # curves hung (Mitsuba 3.9.1, Dr.Jit 1.5, llvm_ad_rgb; the acceleration structure's build
    # waits on work that pool never runs). The load is a small part of the process either way.
    if args.threads > 0:
        dr.set_thread_count(args.threads)

    os.makedirs(args.out_dir, exist_ok=True)

    def render(spp, seed):
        t, c = time.perf_counter(), time.process_time()
        img = np.array(mi.render(scene, spp=spp, seed=seed), dtype=np.float32)[..., :3]
        return time.perf_counter() - t, time.process_time() - c, img

    # Images are written after every render: writing an EXR with a pool of one thread hung as
    # well (the EXR writer's own tasks), so the pool gets a second thread for the writing.
    pending = []

    def save(img, name):
        path = os.path.join(args.out_dir, name)
        pending.append((img, path))
        return path

    renders = []
    seed = args.seed
    for spp in spps:
        times = []
        img = None
        for _ in range(args.reps):
            t, c, img = render(spp, seed)
            seed += 1
            times.append((t, c))
        if not np.isfinite(img).all():
            print(f"Mitsuba's {spp}-spp render holds non-finite values", file=sys.stderr)
            sys.exit(1)
        best = min(times)
        renders.append({"spp": spp, "first_s": times[0][0], "best_s": best[0], "best_cpu_s": best[1],
                        "exr": save(img, f"m_{spp}.exr")})
    reference = None
    if args.ref_spp > 0:
        t, c, img = render(args.ref_spp, 10_000 + args.seed)
        reference = {"spp": args.ref_spp, "s": t, "cpu_s": c, "exr": save(img, "m_ref.exr")}
    threads = dr.thread_count()
    if threads < 2:
        dr.set_thread_count(2)
    for img, path in pending:
        mi.Bitmap(np.ascontiguousarray(img)).write(path)
    out = {
        "mitsuba": mi.__version__,
        "variant": args.variant,
        "threads": threads,
        "python": sys.version.split()[0],
        "startup_s": t_imp - T_START,
        "import_s": import_s,
        "load_s": load_s,
        "renders": renders,
        "reference": reference,
        "process_s": time.perf_counter() - T_START,
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
