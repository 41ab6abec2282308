#!/usr/bin/env python3
"""Score `woven fit` outputs against the ground truth of Mitsuba test sets: a Markdown table and a contact sheet.

    python baseline.py --fits OUT SET_DIR [SET_DIR ...] [--table table.md] [--sheet sheet.png]

For every scene `NAME` of each `SET_DIR/index.json` whose fit is in `OUT/NAME/` (made by run_fits.py):
- true pattern: `SET_DIR/NAME.json` → `pattern` (1 = warp on top, rows = wefts from the TOP of the image down),
  converted to woven's convention by inverting every cell (woven: 1 = weft on top) AND reversing the row order
  (woven lays weft i at world y = (i + 1/2) pitch with the image's up = +y, so its row 0 is the BOTTOM weft;
  src/geometry/yarn.rs, src/render/camera.rs); both reduced to the minimum repeat;
- fitted pattern: `OUT/NAME/fit.json` → `cloth.pattern`;
- equal up to a cyclic shift, and (separate columns) up to inversion, transposition, and transposition with
  inversion (woven's 90° rotation: wefts become warps), each also up to a shift; equal to the inverted truth
  WITHOUT the row reversal (a twill or satin of the opposite direction: what a fit that read the rows the other
  way round would give); the smallest number of cells that differ over all shifts when the sizes agree;
- crop PSNR (the `PSNR x dB` the fit prints: its fit of the one-repeat crop), the full-image PSNR of fit.png
  (the fit's re-render of the whole picture) against the input PNG (8-bit sRGB), the fit's own time and the
  wall time of the run.
The sheet has one row per scene: the input with the fit's crop drawn in red (mapped back through the prep's
homography) | fit.png | |input - fit.png| x 2 | the crop the fit saw | the fit of that crop (from compare.png).
Needs numpy and Pillow.
"""
import argparse
import json
import os
import re
import sys

import numpy as np

from make_set import min_repeat  # the set's own reduction (make_set imports mitsuba only when rendering)


def shift_distance(a, b):
    """Fewest differing cells between `a` and any cyclic shift of `b` (None when the shapes differ)."""
    if a.shape != b.shape:
        return None
    return min(int(np.sum(a != np.roll(b, (i, j), axis=(0, 1))))
               for i in range(a.shape[0]) for j in range(a.shape[1]))


def equal_up_to_shift(a, b):
    """Same pattern with another origin (both already reduced to the minimum repeat)."""
    return shift_distance(a, b) == 0


def parse_rows(rows):
    """['1100', '0110'] or [[1, 1, 0, 0], ...] → int array."""
    if rows and isinstance(rows[0], str):
        return np.array([[int(ch) for ch in r] for r in rows], dtype=int)
    return np.array(rows, dtype=int)


def to_text(p):
    return "/".join("".join(str(int(v)) for v in row) for row in p)


def score(set_dir, name, fit_dir):
    """One table row (dict) for scene `name`; None when its fit is missing."""
    run_path = os.path.join(fit_dir, "run.json")
    if not os.path.exists(run_path):
        return None
    with open(os.path.join(set_dir, name + ".json")) as f:
        meta = json.load(f)
    with open(run_path) as f:
        run = json.load(f)
    mitsuba = np.array(meta["pattern"], dtype=int)
    truth = min_repeat(np.flipud(1 - mitsuba))
    row = {"name": name, "truth": to_text(truth), "truth_shape": truth.shape, "exit": run["exit_code"],
           "wall_s": run["wall_s"], "cpu_s": run.get("cpu_s"),
           "timed_out": run["timed_out"] or run.get("cpu_limited", False), "meta": meta}
    log = "\n".join(run["output_tail"])
    m = re.search(r"PSNR ([-0-9.]+) dB, ([0-9.]+) s", log)
    row["psnr"] = float(m.group(1)) if m else None
    row["fit_s"] = float(m.group(2)) if m else None
    # The grid the preparation found: the fit's own prep.json, or that of `run_fits.py --prep-stopped`.
    for prep_path in (os.path.join(fit_dir, "prep.json"), os.path.join(fit_dir, "prep", "prep.json")):
        if os.path.exists(prep_path):
            with open(prep_path) as f:
                row["prep"] = json.load(f)
            break
    fit_json = os.path.join(fit_dir, "fit.json")
    if run["exit_code"] != 0 or not os.path.exists(fit_json):
        row["fit"] = None
        return row
    with open(fit_json) as f:
        fit = min_repeat(parse_rows(json.load(f)["cloth"]["pattern"]))
    row["fit"] = to_text(fit)
    row["shift"] = equal_up_to_shift(truth, fit)
    row["inverted"] = equal_up_to_shift(1 - truth, fit)
    row["transposed"] = equal_up_to_shift(truth.T, fit)
    row["rot90"] = equal_up_to_shift(1 - truth.T, fit)
    row["unflipped"] = equal_up_to_shift(min_repeat(1 - mitsuba), fit)
    row["cells_off"] = shift_distance(truth, fit)
    fit_png = os.path.join(fit_dir, "fit.png")
    if os.path.exists(fit_png):
        row["full_psnr"] = full_psnr(os.path.join(set_dir, name + ".png"), fit_png)
    return row


def yes(v):
    return "—" if v is None else ("**yes**" if v else "no")


def table(rows):
    """Markdown table of the scored rows."""
    out = ["| image | true (woven: 1 = weft on top) | fitted | = up to shift | inverted | transposed | "
           "transposed+inverted | rows not reversed | cells off | crop PSNR dB | full PSNR dB | fit s | CPU s | wall s |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        cpu = "—" if r.get("cpu_s") is None else f"{r['cpu_s']:.0f}"
        if r["fit"] is None:
            why = "stopped (time limit)" if r["timed_out"] else f"exit {r['exit']}"
            out.append(f"| {r['name']} | `{r['truth']}` | {why} | — | — | — | — | — | — | — | — | — | {cpu} | {r['wall_s']:.0f} |")
            continue
        off = "size differs" if r["cells_off"] is None else str(r["cells_off"])
        psnr = "—" if r["psnr"] is None else f"{r['psnr']:.2f}"
        fit_s = "—" if r["fit_s"] is None else f"{r['fit_s']:.0f}"
        full = "—" if r.get("full_psnr") is None else f"{r['full_psnr']:.2f}"
        out.append(f"| {r['name']} | `{r['truth']}` | `{r['fit']}` | {yes(r['shift'])} | {yes(r['inverted'])} | "
                   f"{yes(r['transposed'])} | {yes(r['rot90'])} | {yes(r['unflipped'])} | {off} | {psnr} | {full} | {fit_s} | {cpu} | {r['wall_s']:.0f} |")
    return "\n".join(out)


def prep_table(rows):
    """Markdown table: what the preparation found against the truth (rotation, yarn pitch, repeat)."""
    out = ["| image | rotation true / found ° | pitch x true / found px | pitch y true / found px | "
           "repeat true (wefts×warps) / found n_e×n_a | crop px |",
           "|---|---|---|---|---|---|"]
    for r in rows:
        m = r["meta"]
        width, height = m["image"]["width"], m["image"]["height"]
        true_px = width / m["warp"]["count_visible"]
        true_py = height / m["weft"]["count_visible"]
        rot = m.get("rotation_deg", 0.0)
        truth = f"{m['pattern_rows']}×{m['pattern_cols']}"
        p = r.get("prep")
        if p is None:
            out.append(f"| {r['name']} | {rot:.2f} / — | {true_px:.1f} / — | {true_py:.1f} / — | {truth} / — | — |")
            continue
        c = p["crop"]
        out.append(f"| {r['name']} | {rot:.2f} / {p['angle_deg']:.2f} | {true_px:.1f} / {p['pitch_x']:.1f} | "
                   f"{true_py:.1f} / {p['pitch_y']:.1f} | {truth} / {p['n_e']}×{p['n_a']} | "
                   f"{c['w']}×{c['h']} |")
    return "\n".join(out)


def summary(rows, label):
    """One line: exact count, mean PSNR, mean times."""
    done = [r for r in rows if r["fit"] is not None]
    if not rows:
        return f"{label}: no fits"
    exact = sum(1 for r in done if r["shift"])
    any_sym = sum(1 for r in done if r["shift"] or r["inverted"] or r["transposed"] or r["rot90"])
    psnr = [r["psnr"] for r in done if r["psnr"] is not None]
    fit_s = [r["fit_s"] for r in done if r["fit_s"] is not None]
    return (f"{label}: {len(done)}/{len(rows)} fits finished; pattern equal up to shift {exact}/{len(rows)}, up to "
            f"shift/inversion/transposition {any_sym}/{len(rows)}; crop PSNR mean "
            f"{np.mean(psnr) if psnr else float('nan'):.2f} dB (min {min(psnr) if psnr else float('nan'):.2f}, "
            f"max {max(psnr) if psnr else float('nan'):.2f}); fit time mean "
            f"{np.mean(fit_s) if fit_s else float('nan'):.0f} s, wall mean {np.mean([r['wall_s'] for r in rows]):.0f} s")


COMPARE_HEADER = 28
"""Height in pixels of the text header of the fit's compare.png."""


def srgb8(path):
    """An 8-bit RGB image as a float array."""
    from PIL import Image
    return np.asarray(Image.open(path).convert("RGB"), dtype=float)


def full_psnr(input_png, fit_png):
    """PSNR (8-bit sRGB, peak 255) of the fit's whole-image re-render `fit.png` against the input; None when
    the sizes differ."""
    a, b = srgb8(input_png), srgb8(fit_png)
    if a.shape != b.shape:
        return None
    mse = float(np.mean((a - b) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(255.0 ** 2 / mse)


def sheet(rows, set_of, fits, path, cell=128):
    """Contact sheet, one row per scene: input with the fit's crop in red | fit.png (the fit's re-render of
    the whole image) | |input - fit.png| x 2 | the crop the fit saw | the fit of that crop (compare.png)."""
    from PIL import Image, ImageDraw
    label_h = 14
    img = Image.new("RGB", (5 * cell, len(rows) * (cell + label_h)), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    for k, r in enumerate(rows):
        y0 = k * (cell + label_h)
        name = r["name"]
        src_path = os.path.join(set_of[name], name + ".png")
        src = Image.open(src_path).convert("RGB")
        sx, sy = cell / src.width, cell / src.height
        thumb = src.resize((cell, cell), Image.BILINEAR)
        fit_dir = os.path.join(fits, name)
        prep_path = os.path.join(fit_dir, "prep.json")
        if os.path.exists(prep_path):
            with open(prep_path) as f:
                prep = json.load(f)
            # The prep's homography maps rectified (output) pixels to input pixels; the crop is in the
            # rectified frame.
            h = np.array(prep["homography"], dtype=float)
            c = prep["crop"]
            corners = [(c["x"], c["y"]), (c["x"] + c["w"], c["y"]), (c["x"] + c["w"], c["y"] + c["h"]),
                       (c["x"], c["y"] + c["h"])]
            pts = []
            for (x, y) in corners:
                q = h @ np.array([x, y, 1.0])
                pts.append((q[0] / q[2] * sx, q[1] / q[2] * sy))
            ImageDraw.Draw(thumb).polygon(pts, outline=(255, 0, 0))
        img.paste(thumb, (0, y0 + label_h))
        compare = os.path.join(fit_dir, "compare.png")
        fit_png = os.path.join(fit_dir, "fit.png")
        if os.path.exists(fit_png):
            fit_img = Image.open(fit_png).convert("RGB")
            img.paste(fit_img.resize((cell, cell), Image.BILINEAR), (cell, y0 + label_h))
            if fit_img.size == src.size:
                err = np.clip(np.abs(srgb8(src_path) - srgb8(fit_png)) * 2, 0, 255).astype(np.uint8)
                img.paste(Image.fromarray(err).resize((cell, cell), Image.BILINEAR), (2 * cell, y0 + label_h))
        if os.path.exists(compare):
            # compare.png (src/fit): a 28 px text header, then crop | fit of the crop | error panels of the
            # crop's aspect, 4 px apart. Each panel is fitted into the cell keeping its aspect.
            cmp_img = Image.open(compare).convert("RGB")
            pw, ph = (cmp_img.width - 8) // 3, cmp_img.height - COMPARE_HEADER
            scale = cell / max(pw, ph)
            w, h = max(1, round(pw * scale)), max(1, round(ph * scale))
            for p in range(2):
                panel = cmp_img.crop((p * (pw + 4), COMPARE_HEADER, p * (pw + 4) + pw, cmp_img.height))
                img.paste(panel.resize((w, h), Image.BILINEAR),
                          ((3 + p) * cell + (cell - w) // 2, y0 + label_h + (cell - h) // 2))
        status = "no fit" if r["fit"] is None else ("pattern OK" if r["shift"] else "pattern WRONG")
        psnr = "" if r.get("psnr") is None else f"crop {r['psnr']:.1f} dB"
        fpsnr = "" if r.get("full_psnr") is None else f"full {r['full_psnr']:.1f} dB"
        draw.text((2, y0 + 1), f"{name}  {status}  {psnr}  {fpsnr}", fill=(0, 0, 0))
    tmp = path + ".tmp.png"
    img.save(tmp)
    os.replace(tmp, path)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sets", nargs="+", help="test-set folders (index.json, NAME.json, NAME.png)")
    ap.add_argument("--fits", required=True, help="folder of fit outputs, one sub-folder per NAME")
    ap.add_argument("--table", help="write the Markdown table and summary here (default: stdout)")
    ap.add_argument("--sheet", help="write the contact sheet PNG here")
    args = ap.parse_args()
    groups, set_of = [], {}
    for d in args.sets:
        try:
            with open(os.path.join(d, "index.json")) as f:
                index = json.load(f)
        except (OSError, json.JSONDecodeError) as e:
            sys.exit(f"error: cannot read {os.path.join(d, 'index.json')}: {e}")
        rows = []
        for e in index:
            set_of[e["name"]] = d
            r = score(d, e["name"], os.path.join(args.fits, e["name"]))
            if r is not None:
                rows.append(r)
        groups.append((d, rows))
    text = []
    for d, rows in groups:
        text.append(f"### {d}\n\n{summary(rows, os.path.basename(os.path.normpath(d)))}\n\n{table(rows)}\n\n"
                    f"Preparation (grid and crop):\n\n{prep_table(rows)}\n")
    out = "\n".join(text)
    if args.table:
        tmp = args.table + ".tmp"
        with open(tmp, "w") as f:
            f.write(out)
        os.replace(tmp, args.table)
    else:
        print(out)
    if args.sheet:
        sheet([r for _, rows in groups for r in rows], set_of, args.fits, args.sheet)


if __name__ == "__main__":
    main()
