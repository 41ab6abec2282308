#!/usr/bin/env python3
"""Random Mitsuba 3 renders of woven cloth with ground truth: a cross-renderer test set for `woven fit`.

    python make_set.py --out DIR --count N --seed S [--spp 96] [--size 256] [--variant scalar_rgb]

Scene `k` (0-based) of seed `S` is drawn from its own generator `numpy.random.default_rng([S, k])`, so any one
scene can be re-made alone (`--first k --count 1`) and an interrupted run resumes (scenes whose `NAME.json`
exists are skipped). Output per scene, in the format and conventions of the hand-made Mitsuba development set:
`NAME.exr` (linear float RGB), `NAME.png` (8-bit sRGB, clipped), `NAME.json` (every parameter and the ground
truth), `NAME_labels.png` (R/G/B = warp/weft/background coverage per pixel), `NAME_gt.npz` (`warp_cov`,
`weft_cov`, `bg_cov`, `height`), and `index.json` listing all scenes of the folder. See README.md for the fields.

Geometry. Pattern `P` (rows = weft yarns along image x, top to bottom; columns = warp yarns along image y,
left to right; 1 = WARP on top). Warp yarn `n` runs along world y at x = (n + 1/2) s_warp; weft yarn `m` runs
along world x at y = -(m + 1/2) s_weft, so rows go down the image. Each yarn is a constant-radius tube around
a periodic uniform cubic B-spline centre curve (Mitsuba `bsplinecurve`) whose control points sit above the
crossings. The control heights are solved so that the curve *interpolates* the pattern heights at every
crossing: z = +h where the yarn is on top, -h where it is underneath, with h = crimp (r_warp + r_weft) / 2, so
the two tubes just touch at each crossing when crimp = 1. A uniform cubic B-spline evaluated at its knots is
(c[k-1] + 4 c[k] + c[k+1]) / 6 (de Boor, "A Practical Guide to Splines", uniform cubic case), so the control
heights of one period solve that circulant system.

Ground truth comes from ray casting with the same camera: a second render in which the warp and weft tubes are
red and green area emitters and everything else (background plane or environment) is blue, with a path depth
of 1 (only directly seen emission) and a 4x4 stratified grid per pixel, gives the coverage fractions exactly
(up to the 1/16 sampling); an `aov` render of hit positions on the same grid gives the mean yarn height.
Each scene is then checked: at the centre pixel of every crossing inside the image the coverage of the yarn
that `P` puts on top must exceed 1/2; a failure aborts the run (it would mean the pattern, camera and geometry
disagree).
"""
import argparse
import json
import math
import os
import sys
import tempfile
import time

import numpy as np

# ----------------------------------------------------------------------------------------------------------
# Patterns (1 = warp on top)
# ----------------------------------------------------------------------------------------------------------


def twill(over, under, direction):
    """Twill `over`/`under`: each warp goes over `over` wefts and under `under`; with rows running down the
    image, direction +1 shifts each row one column right, a diagonal from top-left to bottom-right (an S twill
    '\\'), and -1 gives the Z twill '/'."""
    n = over + under
    return np.array([[1 if (j - direction * i) % n < over else 0 for j in range(n)] for i in range(n)])


def satin(n, step):
    """Regular satin of `n` ends: one warp over per row, at column (i * step) mod n (a weft-faced satin;
    invert it for the warp-faced one). `step` must be coprime with `n` and not ±1 (else it is a twill)."""
    p = np.zeros((n, n), dtype=int)
    for i in range(n):
        p[i, (i * step) % n] = 1
    return p


def satin4_broken():
    """The 4-end 'broken crow' satin: no regular 4-end satin exists (no step coprime with 4 other than ±1),
    so the interlacings move by 1, 2, 1, 2 columns."""
    p = np.zeros((4, 4), dtype=int)
    for i, j in enumerate([0, 1, 3, 2]):
        p[i, j] = 1
    return p


def basket(k):
    """Basket k×k: blocks of k warps and k wefts interlace like a plain weave."""
    return np.array([[((i // k) + (j // k)) % 2 for j in range(2 * k)] for i in range(2 * k)])


def warp_rib(k):
    """Warp rib k: each warp goes over k wefts and under k, neighbouring warps opposite (2k rows × 2 cols)."""
    return np.array([[((i // k) + j) % 2 for j in range(2)] for i in range(2 * k)])


def herringbone(over, under, run):
    """Herringbone: a twill `over`/`under` whose diagonal reverses every `run` warps (2 run columns)."""
    n = over + under
    cols = []
    for j in range(2 * run):
        jj = j if j < run else 2 * run - 1 - j
        cols.append([1 if (jj - i) % n < over else 0 for i in range(n)])
    return np.array(cols).T


def holds_together(p):
    """True when every weft (row) and every warp (column) changes side at least once in the repeat: a yarn
    that stays on one side of every crossing would float loose over the whole fabric."""
    return bool(np.all(p.min(axis=1) == 0) and np.all(p.max(axis=1) == 1)
                and np.all(p.min(axis=0) == 0) and np.all(p.max(axis=0) == 1))


def min_repeat(p):
    """Smallest (r, c) dividing the shape with which `p` repeats; returns that sub-block."""
    rows, cols = p.shape
    for r in range(1, rows + 1):
        if rows % r == 0 and np.array_equal(p, np.tile(p[:r], (rows // r, 1))):
            break
    for c in range(1, cols + 1):
        if cols % c == 0 and np.array_equal(p, np.tile(p[:, :c], (1, cols // c))):
            break
    return p[:r, :c]


def draw_pattern(rng):
    """A random pattern family with random variant, orientation and origin; returns (P, name)."""
    family = rng.choice(["plain", "twill", "satin", "basket", "rib", "herringbone", "random"],
                        p=[0.12, 0.26, 0.18, 0.09, 0.09, 0.11, 0.15])
    transpose_ok = True
    if family == "plain":
        p, name = np.array([[1, 0], [0, 1]]), "plain"
        transpose_ok = False
    elif family == "twill":
        over, under = [(2, 1), (1, 2), (2, 2), (3, 1), (1, 3)][rng.integers(5)]
        direction = int(rng.choice([1, -1]))
        p = twill(over, under, direction)
        name = f"twill{over}{under}{'s' if direction > 0 else 'z'}"
    elif family == "satin":
        n = int(rng.choice([4, 5, 8]))
        if n == 4:
            p, name = satin4_broken(), "satin4"
        else:
            step = int(rng.choice({5: [2, 3], 8: [3, 5]}[n]))
            p, name = satin(n, step), f"satin{n}s{step}"
        if rng.random() < 0.5:
            p, name = 1 - p, name + "warpfaced"
    elif family == "basket":
        k = int(rng.choice([2, 2, 3]))
        p, name = basket(k), f"basket{k}"
        transpose_ok = False
    elif family == "rib":
        k = int(rng.choice([2, 3]))
        p, name = warp_rib(k), f"warprib{k}"
        if rng.random() < 0.5:
            p, name = p.T, f"weftrib{k}"
        transpose_ok = False
    elif family == "herringbone":
        over, under = [(2, 2), (2, 1), (3, 1)][rng.integers(3)]
        run = int(rng.choice([over + under, 2 * (over + under)])) if over + under < 4 else over + under
        p, name = herringbone(over, under, run), f"herringbone{over}{under}r{run}"
    else:
        while True:
            rows, cols = int(rng.integers(3, 7)), int(rng.integers(3, 7))
            q = (rng.random((rows, cols)) < rng.uniform(0.3, 0.7)).astype(int)
            q = min_repeat(q)
            if holds_together(q) and max(q.shape) >= 3:
                break
        p, name = q, f"random{q.shape[0]}x{q.shape[1]}"
        transpose_ok = False
    if transpose_ok and rng.random() < 0.5:
        p, name = p.T, name + "T"
    # A random origin: which crossing of the repeat lands at the top-left of the image.
    p = np.roll(p, (int(rng.integers(p.shape[0])), int(rng.integers(p.shape[1]))), axis=(0, 1))
    p = min_repeat(p)
    if not holds_together(p):
        raise AssertionError(f"pattern {name} does not hold together: {p.tolist()}")
    return p.astype(int), name


# ----------------------------------------------------------------------------------------------------------
# Colours, materials, lights
# ----------------------------------------------------------------------------------------------------------


def srgb_to_linear(c):
    """IEC 61966-2-1 sRGB decoding."""
    c = np.asarray(c, dtype=float)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(c):
    """IEC 61966-2-1 sRGB encoding (input clipped to [0, 1])."""
    c = np.clip(c, 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1 / 2.4) - 0.055)


def hsv_to_rgb(h, s, v):
    """HSV (all in [0, 1]) to RGB (display values, here taken as sRGB)."""
    i = int(h * 6.0) % 6
    f = h * 6.0 - math.floor(h * 6.0)
    p, q, t = v * (1 - s), v * (1 - s * f), v * (1 - s * (1 - f))
    return [(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i]


def draw_colour(rng):
    """A random yarn colour (sRGB hue/saturation/value; a quarter of them near-grey)."""
    h = rng.random()
    s = rng.uniform(0.0, 0.15) if rng.random() < 0.25 else rng.uniform(0.3, 0.9)
    v = rng.uniform(0.2, 0.95)
    return (h, s, v)


def draw_colours(rng):
    """Warp and weft colours (linear RGB) and how they relate: 'different', 'similar' or 'same'."""
    mode = rng.choice(["different", "similar", "same"], p=[0.55, 0.3, 0.15])
    a = draw_colour(rng)
    if mode == "different":
        while True:
            b = draw_colour(rng)
            hue_gap = min(abs(a[0] - b[0]), 1 - abs(a[0] - b[0]))
            if abs(a[2] - b[2]) > 0.25 or (hue_gap > 0.15 and min(a[1], b[1]) > 0.3):
                break
    elif mode == "similar":
        # Same hue family, value 15-35 % darker or lighter: a low-contrast pair.
        factor = rng.uniform(0.65, 0.85)
        value = a[2] * factor if rng.random() < 0.5 else a[2] / factor
        b = ((a[0] + rng.uniform(-0.04, 0.04)) % 1.0, float(np.clip(a[1] * rng.uniform(0.8, 1.2), 0, 1)),
             float(np.clip(value, 0.05, 0.97)))
    else:
        b = a
    ca = srgb_to_linear(hsv_to_rgb(*a))
    cb = srgb_to_linear(hsv_to_rgb(*b))
    if rng.random() < 0.5:
        ca, cb = cb, ca
    return [round(float(x), 4) for x in ca], [round(float(x), 4) for x in cb], str(mode)


def draw_material(rng):
    """Material type and parameters shared by both yarn sets (only the colour differs)."""
    kind = str(rng.choice(["principled", "roughplastic", "diffuse"], p=[0.45, 0.35, 0.2]))
    if kind == "principled":
        return {"type": kind, "roughness": round(rng.uniform(0.3, 0.9), 3),
                "sheen": round(rng.uniform(0.0, 0.8), 3), "sheen_tint": round(rng.uniform(0.0, 1.0), 3),
                "specular": round(rng.uniform(0.2, 0.6), 3), "metallic": 0.0}
    if kind == "roughplastic":
        return {"type": kind, "alpha": round(float(np.exp(rng.uniform(np.log(0.08), np.log(0.4)))), 4),
                "distribution": str(rng.choice(["ggx", "beckmann"])), "int_ior": round(rng.uniform(1.4, 1.6), 3),
                "nonlinear": bool(rng.random() < 0.5)}
    return {"type": kind}


def bsdf_dict(material, colour):
    """The Mitsuba BSDF of one yarn set."""
    rgb = {"type": "rgb", "value": list(colour)}
    kind = material["type"]
    if kind == "principled":
        d = {k: v for k, v in material.items()}
        d["base_color"] = rgb
        return d
    if kind == "roughplastic":
        d = {k: v for k, v in material.items()}
        d["diffuse_reflectance"] = rgb
        return d
    return {"type": "diffuse", "reflectance": rgb}


def direction_from(elevation_deg, azimuth_deg, from_below=False):
    """Propagation direction (Mitsuba's `direction`) of light arriving from elevation/azimuth (degrees above
    the cloth plane, azimuth from +x towards +y); `from_below` mirrors it under the cloth."""
    el, az = math.radians(elevation_deg), math.radians(azimuth_deg)
    towards_light = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    if from_below:
        towards_light[2] = -towards_light[2]
    return [round(float(x), 6) for x in -towards_light]


TONES = {"black": (0.0, 0.02), "grey": (0.15, 0.4), "white": (0.7, 0.95)}


def draw_lights(rng, extent, cloth_top, cloth_bottom, centre):
    """A light set-up and background. Returns (lights json, dict of Mitsuba scene entries, background json)."""
    setup = str(rng.choice(["front", "front_back", "rig", "area", "env"], p=[0.2, 0.2, 0.25, 0.2, 0.15]))
    tone = str(rng.choice(list(TONES)))
    level = round(rng.uniform(*TONES[tone]), 3)
    az = rng.uniform(0, 360)
    entries, lights = {}, {"setup": setup, "directional": {}}

    def directional(key, el, azimuth, irradiance, below=False):
        d = direction_from(el, azimuth, below)
        entries["light_" + key] = {"type": "directional", "direction": d, "irradiance": irradiance}
        lights["directional"][key] = {"direction": d, "irradiance": irradiance, "elevation_deg": round(el, 2),
                                      "azimuth_deg": round(azimuth % 360, 2), "from_below": below}

    def constant_env(radiance):
        entries["ambient"] = {"type": "constant", "radiance": {"type": "rgb", "value": radiance}}
        lights["ambient_radiance"] = radiance
        lights["ambient_visible"] = True

    background = {"tone": tone}
    if setup in ("front", "area"):
        # A diffuse plane under the cloth (a table): lit by the same lights, shadowed by the cloth.
        gap = round(rng.uniform(0.3, 2.0), 3)
        z = cloth_bottom - gap
        background.update({"kind": "plane", "albedo": level, "z": round(z, 4), "gap_below_cloth": gap})
        entries["background_plane"] = {
            "type": "rectangle",
            "to_world": _translate_scale([centre[0], centre[1], z], 3.0 * extent),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [level] * 3}},
        }
        ambient = round(rng.uniform(0.0, 0.08), 3) if rng.random() < 0.5 else 0.0
        if ambient > 0:
            constant_env(ambient)
        if setup == "front":
            directional("front", rng.uniform(35, 80), az, round(rng.uniform(2.0, 4.0), 3))
        else:
            # A rectangular area light beside and above the cloth, outside the camera's view (the camera's
            # rays start just above the cloth, see `sensor_dict`), giving soft shading and soft shadows.
            el = rng.uniform(35, 70)
            dist = rng.uniform(2.0, 3.5) * extent
            half = rng.uniform(0.15, 0.5) * extent
            towards = -np.array(direction_from(el, az))
            pos = np.array([centre[0], centre[1], 0.0]) + dist * towards
            irradiance = rng.uniform(2.0, 4.0)
            area = (2 * half) ** 2
            # Irradiance at the cloth centre of a small rectangle facing it: E = L A cos(theta) / d^2.
            radiance = irradiance * dist ** 2 / (area * math.sin(math.radians(el)))
            import mitsuba as mi
            entries["light_area"] = {
                "type": "rectangle",
                "to_world": mi.ScalarTransform4f().look_at(origin=pos.tolist(), target=[centre[0], centre[1], 0.0],
                                                           up=[0, 0, 1] if el < 89 else [0, 1, 0])
                @ mi.ScalarTransform4f().scale([half, half, 1.0]),
                "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [radiance] * 3}},
            }
            lights["area"] = {"position": [round(float(x), 4) for x in pos], "half_size": round(half, 4),
                              "elevation_deg": round(el, 2), "azimuth_deg": round(az, 2),
                              "radiance": round(radiance, 4), "irradiance_at_centre": round(irradiance, 3)}
    else:
        background.update({"kind": "environment", "radiance": level})
        if setup == "front_back":
            constant_env(level)
            directional("front", rng.uniform(35, 80), az, round(rng.uniform(2.0, 4.0), 3))
            directional("back", rng.uniform(40, 90), az + rng.uniform(-90, 90), round(rng.uniform(0.5, 2.0), 3),
                        below=True)
        elif setup == "rig":
            # The development set's kind of rig: ambient, top light, back light, two side lights.
            constant_env(level)
            directional("top", 90 - rng.uniform(15, 40), az, round(rng.uniform(1.5, 3.0), 3))
            if rng.random() < 0.8:
                directional("back", 90 - rng.uniform(15, 40), az + 180, round(rng.uniform(0.5, 1.5), 3), below=True)
            side = round(rng.uniform(0.3, 0.9), 3)
            directional("left", 90 - rng.uniform(50, 70), az + 90, side)
            directional("right", 90 - rng.uniform(50, 70), az - 90, side)
        else:
            lights.update(_sky_environment(rng, level, entries))
    return lights, entries, background


def _translate_scale(t, s):
    import mitsuba as mi
    return mi.ScalarTransform4f().translate(t) @ mi.ScalarTransform4f().scale([s, s, 1.0])


def _sky_environment(rng, ground, entries):
    """A procedural environment map: a sky whose radiance falls from zenith to horizon, a sun (a Gaussian
    lobe), and a uniform lower hemisphere of radiance `ground` (what the gaps show). Written as a
    lat-long EXR; Mitsuba's envmap has +y up, so the map is rotated by +90° about x to put +y on +z."""
    import mitsuba as mi
    width, height = 256, 128
    sun_el = rng.uniform(30, 75)
    sun_az = rng.uniform(0, 360)
    sun_width = rng.uniform(3.0, 8.0)
    sky_zenith = rng.uniform(0.2, 0.6)
    sun_irradiance = rng.uniform(1.5, 3.0)
    tint = np.array([rng.uniform(0.8, 1.0), rng.uniform(0.85, 1.0), 1.0])
    sun_dir = -np.array(direction_from(sun_el, sun_az))
    # Texel centres -> local direction, Mitsuba envmap convention: u = atan2(x, -z) / 2pi, v = acos(y) / pi.
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(height) + 0.5) / height
    phi, theta = np.meshgrid(2 * np.pi * u, np.pi * v)
    local = np.stack([np.sin(theta) * np.sin(phi), np.cos(theta), -np.sin(theta) * np.cos(phi)], -1)
    # Rotation by +90° about x: (x, y, z) -> (x, -z, y) maps local +y to world +z.
    world = np.stack([local[..., 0], -local[..., 2], local[..., 1]], -1)
    up = world[..., 2]
    sky = np.where(up > 0, sky_zenith * (0.35 + 0.65 * np.clip(up, 0, 1)), ground)[..., None] * tint
    ang = np.degrees(np.arccos(np.clip(world @ sun_dir, -1, 1)))
    lobe = np.exp(-0.5 * (ang / sun_width) ** 2)
    # Normalize the lobe so its irradiance on the cloth plane is `sun_irradiance`.
    solid = (2 * np.pi / width) * (np.pi / height) * np.sin(theta)
    lobe_irr = float(np.sum(lobe * solid * np.clip(up, 0, None)))
    sky = sky + (sun_irradiance / lobe_irr) * lobe[..., None] * np.array([1.0, 0.97, 0.9])
    fd, path = tempfile.mkstemp(suffix=".exr", prefix="woven_sky_")
    os.close(fd)
    mi.Bitmap(sky.astype(np.float32)).write(path)
    entries["environment"] = {"type": "envmap", "filename": path,
                              "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], 90)}
    entries["_tmpfile"] = path
    return {"environment_map": {"sun_elevation_deg": round(sun_el, 2), "sun_azimuth_deg": round(sun_az, 2),
                                "sun_lobe_sigma_deg": round(sun_width, 2), "sun_irradiance": round(sun_irradiance, 3),
                                "sky_zenith_radiance": round(sky_zenith, 3), "sky_tint": [round(float(x), 3) for x in tint],
                                "ground_radiance": ground, "resolution": [width, height]},
            "ambient_visible": True}


# ----------------------------------------------------------------------------------------------------------
# Geometry
# ----------------------------------------------------------------------------------------------------------


def interp_controls(values):
    """Control heights c of a periodic uniform cubic B-spline with (c[k-1] + 4 c[k] + c[k+1]) / 6 = values[k]
    for every k (indices modulo the period)."""
    n = len(values)
    a = np.zeros((n, n))
    for k in range(n):
        a[k, (k - 1) % n] += 1 / 6
        a[k, k] += 4 / 6
        a[k, (k + 1) % n] += 1 / 6
    return np.linalg.solve(a, np.asarray(values, dtype=float))


def write_curves(path, p, geo, span):
    """Write the warp and weft centre curves of pattern `p` as Mitsuba curve files (`x y z radius` per
    control point, one blank line between curves). `span` = (n0, n1, m0, m1): the warp indices n0..n1 and
    weft indices m0..m1 to lay, covering the camera's view with margin."""
    rows, cols = p.shape
    n0, n1, m0, m1 = span
    h = geo["height"]
    sa, se = geo["warp_spacing"], geo["weft_spacing"]
    warp_lines, weft_lines = [], []
    for n in range(n0, n1 + 1):
        j = n % cols
        c = interp_controls([h if p[i, j] == 1 else -h for i in range(rows)])
        x = (n + 0.5) * sa
        for m in range(m0 - 1, m1 + 2):
            warp_lines.append(f"{x:.6f} {-(m + 0.5) * se:.6f} {c[m % rows]:.6f} {geo['warp_radius']:.6f}")
        warp_lines.append("")
    for m in range(m0, m1 + 1):
        i = m % rows
        c = interp_controls([-h if p[i, j] == 1 else h for j in range(cols)])
        y = -(m + 0.5) * se
        for n in range(n0 - 1, n1 + 2):
            weft_lines.append(f"{(n + 0.5) * sa:.6f} {y:.6f} {c[n % cols]:.6f} {geo['weft_radius']:.6f}")
        weft_lines.append("")
    for name, lines in (("warp", warp_lines), ("weft", weft_lines)):
        with open(f"{path}_{name}.txt", "w") as f:
            f.write("\n".join(lines))
    return f"{path}_warp.txt", f"{path}_weft.txt"


def camera_frame(view):
    """World-space image axes: (centre, right, up) unit vectors in the cloth plane for rotation theta.
    Positive rotation_deg turns the image axes counter-clockwise over the cloth (the cloth appears turned
    clockwise in the image)."""
    t = math.radians(view["rotation_deg"])
    right = np.array([math.cos(t), math.sin(t)])
    up = np.array([-math.sin(t), math.cos(t)])
    return np.array(view["centre"]), right, up


def sensor_dict(view, size, spp, seed, sampler="independent", cloth_top=1.0):
    """Orthographic camera looking along -z over a `window` × `window` square, turned by rotation_deg.
    Rays start 1 unit above the cloth top (near clip), so lights placed above never block the view."""
    import mitsuba as mi
    centre, right, up = camera_frame(view)
    cam_z = 100.0
    half = view["window"] / 2
    to_world = (mi.ScalarTransform4f().look_at(origin=[centre[0], centre[1], cam_z],
                                               target=[centre[0], centre[1], 0.0], up=[up[0], up[1], 0.0])
                @ mi.ScalarTransform4f().scale([half, half, 1.0]))
    s = {"type": "independent", "sample_count": spp, "seed": seed}
    if sampler == "stratified":
        s = {"type": "stratified", "sample_count": spp, "jitter": False, "seed": seed}
    return {"type": "orthographic", "to_world": to_world, "near_clip": cam_z - (cloth_top + 1.0), "far_clip": 1e4,
            "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"},
                     "pixel_format": "rgb"},
            "sampler": s}


def crossing_pixel(view, geo, size, m, n):
    """Continuous pixel coordinates (row, col), (0, 0) = top-left corner, of the centre of crossing
    (weft m, warp n)."""
    centre, right, up = camera_frame(view)
    pt = np.array([(n + 0.5) * geo["warp_spacing"], -(m + 0.5) * geo["weft_spacing"]]) - centre
    w = view["window"]
    u, v = pt @ right, pt @ up
    return (w / 2 - v) * size / w, (u + w / 2) * size / w


# ----------------------------------------------------------------------------------------------------------
# One scene
# ----------------------------------------------------------------------------------------------------------


def draw_scene(seed, index):
    """Every random choice of scene `index` of `seed` (no rendering)."""
    rng = np.random.default_rng([seed, index])
    p, pattern_name = draw_pattern(rng)
    rows, cols = p.shape
    warp_spacing = 1.0
    weft_spacing = round(rng.uniform(0.75, 1.3), 3) if rng.random() < 0.35 else 1.0
    r_warp = round(rng.uniform(0.30, 0.45) * warp_spacing, 3)
    if rng.random() < 0.35:
        r_weft = round(float(np.clip(r_warp * rng.uniform(0.75, 1.3), 0.22, 0.47 * weft_spacing)), 3)
    else:
        r_weft = round(min(r_warp, 0.47 * weft_spacing), 3)
    crimp = round(rng.uniform(1.0, 1.15), 3)
    geo = {"warp_radius": r_warp, "weft_radius": r_weft, "warp_spacing": warp_spacing,
           "weft_spacing": weft_spacing, "crimp": crimp, "height": round(crimp * (r_warp + r_weft) / 2, 4)}
    # Repeats across the image: 2-8 along x, at most 36 yarns across either way (>= 7 px per yarn at 256 px).
    max_x = max(2, min(8, 36 // cols))
    tiles_x = int(rng.integers(2, max_x + 1))
    window = tiles_x * cols * warp_spacing
    while window / weft_spacing > 36 and tiles_x > 2:
        tiles_x -= 1
        window = tiles_x * cols * warp_spacing
    tiles_y = window / (rows * weft_spacing)
    rotation = round(float(rng.uniform(0, 8) * rng.choice([-1, 1])), 3)
    phase = [round(rng.uniform(0, 1), 3), round(rng.uniform(0, 1), 3)]
    # Unrotated, zero-phase window: top-left corner at world (0, 0); the phase slides it by a fraction of a
    # yarn spacing to the right and down.
    centre = [window / 2 + phase[0] * warp_spacing, -window / 2 - phase[1] * weft_spacing]
    view = {"window": window, "rotation_deg": rotation, "centre": centre, "phase_yarns": phase}
    warp_colour, weft_colour, colour_mode = draw_colours(rng)
    material = draw_material(rng)
    return {"rng": rng, "pattern": p, "pattern_name": pattern_name, "geo": geo, "tiles_x": tiles_x,
            "tiles_y": tiles_y, "view": view, "warp_colour": warp_colour, "weft_colour": weft_colour,
            "colour_mode": colour_mode, "material": material}


def atomic_write_bytes(path, data):
    """Write bytes through a temporary file in the same folder + rename."""
    tmp = path + ".tmp"
    with open(tmp, "wb") as f:
        f.write(data)
    os.replace(tmp, path)


def atomic_write_json(path, obj):
    """Write JSON through a temporary file + rename."""
    atomic_write_bytes(path, (json.dumps(obj, indent=1) + "\n").encode())


def write_png(path, arr_uint8):
    """8-bit RGB PNG, written atomically."""
    import mitsuba as mi
    tmp = path + ".tmp.png"
    mi.Bitmap(np.ascontiguousarray(arr_uint8), pixel_format=mi.Bitmap.PixelFormat.RGB).write(tmp)
    os.replace(tmp, path)


def write_exr(path, arr_float):
    """Linear float32 RGB OpenEXR, written atomically."""
    import mitsuba as mi
    tmp = path + ".tmp.exr"
    mi.Bitmap(np.ascontiguousarray(arr_float.astype(np.float32)), pixel_format=mi.Bitmap.PixelFormat.RGB).write(tmp)
    os.replace(tmp, path)


def make_scene(out, seed, index, size, spp, variant, workdir):
    """Draw, render, label, check and write scene `index`; returns its index.json entry."""
    import mitsuba as mi
    s = draw_scene(seed, index)
    rng, p, geo, view = s["rng"], s["pattern"], s["geo"], s["view"]
    rows, cols = p.shape
    centre, right, up = camera_frame(view)
    # Yarns to lay: every warp/weft whose line passes within the view's bounding circle, plus 3 on each side.
    radius = view["window"] / math.sqrt(2) + 3.0
    n0 = math.floor((centre[0] - radius) / geo["warp_spacing"]) - 3
    n1 = math.ceil((centre[0] + radius) / geo["warp_spacing"]) + 3
    m0 = math.floor((-centre[1] - radius) / geo["weft_spacing"]) - 3
    m1 = math.ceil((-centre[1] + radius) / geo["weft_spacing"]) + 3
    name_stub = f"m{seed}_{index + 1:02d}_{s['pattern_name']}_{s['material']['type']}"
    warp_file, weft_file = write_curves(os.path.join(workdir, name_stub), p, geo, (n0, n1, m0, m1))
    cloth_top = geo["height"] + max(geo["warp_radius"], geo["weft_radius"])
    extent = view["window"]
    lights, light_entries, background = draw_lights(rng, extent, cloth_top, -cloth_top, centre)
    name = f"{name_stub}_{lights['setup']}_{background['tone']}"
    tmpfile = light_entries.pop("_tmpfile", None)
    render_seed = int(seed * 1000 + index)
    scene = {"type": "scene", "integrator": {"type": "path", "max_depth": 8},
             "sensor": sensor_dict(view, size, spp, render_seed, cloth_top=cloth_top),
             "warp": {"type": "bsplinecurve", "filename": warp_file,
                      "bsdf": bsdf_dict(s["material"], s["warp_colour"])},
             "weft": {"type": "bsplinecurve", "filename": weft_file,
                      "bsdf": bsdf_dict(s["material"], s["weft_colour"])}}
    scene.update(light_entries)
    t0 = time.monotonic()
    sc = mi.load_dict(scene)
    t1 = time.monotonic()
    img = np.array(mi.render(sc), dtype=np.float32)[..., :3]
    t2 = time.monotonic()

    # Ground truth: coverage from emissive labels, height from hit positions, 4x4 grid per pixel.
    def emitter(rgb):
        return {"type": "area", "radiance": {"type": "rgb", "value": rgb}}
    black = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}}
    label_scene = {"type": "scene", "integrator": {"type": "path", "max_depth": 1, "hide_emitters": False},
                   "sensor": sensor_dict(view, size, 16, 1, "stratified", cloth_top=cloth_top),
                   "warp": {"type": "bsplinecurve", "filename": warp_file, "bsdf": black,
                            "emitter": emitter([1.0, 0.0, 0.0])},
                   "weft": {"type": "bsplinecurve", "filename": weft_file, "bsdf": black,
                            "emitter": emitter([0.0, 1.0, 0.0])},
                   "bg": {"type": "constant", "radiance": {"type": "rgb", "value": [0.0, 0.0, 1.0]}}}
    if "background_plane" in light_entries:
        plane = dict(light_entries["background_plane"])
        plane["bsdf"] = black
        plane["emitter"] = emitter([0.0, 0.0, 1.0])
        label_scene["background_plane"] = plane
    cov = np.array(mi.render(mi.load_dict(label_scene)), dtype=np.float64)[..., :3]
    aov_scene = {"type": "scene", "integrator": {"type": "aov", "aovs": "p:position"},
                 "sensor": sensor_dict(view, size, 16, 1, "stratified", cloth_top=cloth_top),
                 "warp": {"type": "bsplinecurve", "filename": warp_file, "bsdf": black},
                 "weft": {"type": "bsplinecurve", "filename": weft_file, "bsdf": black}}
    pos = np.array(mi.render(mi.load_dict(aov_scene)), dtype=np.float64)
    t3 = time.monotonic()
    cov = np.clip(cov, 0.0, 1.0)
    total = cov.sum(-1)
    if np.abs(total - 1.0).max() > 1e-3:
        raise AssertionError(f"{name}: label coverages do not sum to 1 (max error {np.abs(total - 1).max():.4f})")
    yarn = cov[..., 0] + cov[..., 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        height = np.where(yarn > 1e-6, pos[..., 2] / yarn, np.nan).astype(np.float32)

    # Check the conventions: the yarn P puts on top covers the centre pixel of each crossing in view.
    checked, failures = 0, []
    for m in range(m0, m1 + 1):
        for n in range(n0, n1 + 1):
            r, c = crossing_pixel(view, geo, size, m, n)
            if 2 <= r < size - 2 and 2 <= c < size - 2:
                top = 0 if p[m % rows, n % cols] == 1 else 1
                checked += 1
                if cov[int(r), int(c), top] <= 0.5:
                    failures.append([m, n])
    if checked == 0 or failures:
        raise AssertionError(f"{name}: {len(failures)} of {checked} crossing centres show the wrong yarn "
                             f"(first: {failures[:5]}); pattern, camera and geometry disagree")

    # Exposure: like a camera's auto-exposure, scale so the 99th percentile of yarn-pixel luminance is at
    # most 0.95 and at least 0.5 (recorded in the JSON; colours in the JSON are albedos, not pixel values).
    lum = img @ np.array([0.2126, 0.7152, 0.0722])
    p99 = float(np.percentile(lum[yarn > 0.5], 99))
    if not np.all(np.isfinite(img)) or not p99 > 0:
        raise AssertionError(f"{name}: the render is not finite or the yarns are black (p99 luminance {p99})")
    exposure = 1.0
    if p99 > 0.95:
        exposure = 0.95 / p99
    elif p99 < 0.5:
        exposure = 0.5 / p99
    img = img * exposure
    base = os.path.join(out, name)
    write_exr(base + ".exr", img)
    write_png(base + ".png", np.round(linear_to_srgb(img) * 255).astype(np.uint8))
    write_png(base + "_labels.png", np.round(cov * 255).astype(np.uint8))
    buf = base + "_gt.tmp.npz"
    np.savez_compressed(buf, warp_cov=cov[..., 0].astype(np.float32), weft_cov=cov[..., 1].astype(np.float32),
                        bg_cov=cov[..., 2].astype(np.float32), height=height)
    os.replace(buf, base + "_gt.npz")
    if tmpfile:
        os.remove(tmpfile)
    for f in (warp_file, weft_file):
        os.remove(f)

    w = view["window"]
    meta = {
        "renderer": "mitsuba3", "mitsuba_version": mi.__version__, "variant": variant,
        "generator": "datagen/mitsuba/make_set.py", "seed": seed, "index": index,
        "conventions": {
            "pattern": "P[i][j]: i = weft yarn (image row direction, top->bottom), j = warp yarn (image column "
                       "direction, left->right); 1 = warp on top at that crossing, 0 = weft on top",
            "warp_axis": "world y (image vertical when rotation_deg = 0)",
            "weft_axis": "world x (image horizontal when rotation_deg = 0)",
            "yarns": "warp n (any integer) at x = (n + 0.5) * warp.spacing, column j = n mod cols; weft m at "
                     "y = -(m + 0.5) * weft.spacing, row i = m mod rows; cloth mid-plane z = 0",
            "camera": "orthographic, looking along -z over a window x window square centred at view.centre; "
                      "image right = (cos t, sin t), image up = (-sin t, cos t) in world xy, t = rotation_deg "
                      "(positive: the cloth appears turned clockwise in the image)",
            "pixel_to_world": "u = (col + 0.5) * window / width - window/2, v = window/2 - (row + 0.5) * window "
                              "/ height; (x, y) = view.centre + u * right + v * up",
            "crossing_center_pixel": "(row, col) = (window/2 - v) * height/window, (u + window/2) * width/window) "
                                     "with (u, v) = ((q - centre).right, (q - centre).up), q = ((n + 0.5) * "
                                     "warp.spacing, -(m + 0.5) * weft.spacing); continuous pixel coords, (0, 0) "
                                     "= top-left corner. With rotation 0 and phase 0 this is the development "
                                     "set's ((ty*R + i + 0.5) * height/(R*tiles_y), (tx*C + j + 0.5) * "
                                     "width/(C*tiles_x))",
            "tiles": "tiles_x = window / (cols * warp.spacing) (an integer), tiles_y = window / (rows * "
                     "weft.spacing) (fractional when the spacings differ): pattern repeats across the image "
                     "before rotation",
            "colors": "linear RGB", "png": "8-bit sRGB transfer, clipped", "exr": "linear float32 RGB",
            "exposure": "the EXR/PNG are the render times `exposure`",
            "light_direction": "direction of propagation (Mitsuba)",
        },
        "pattern": p.tolist(), "pattern_name": s["pattern_name"], "pattern_rows": rows, "pattern_cols": cols,
        "warp_on_top_fraction": float(p.mean()),
        "tiles_x": s["tiles_x"], "tiles_y": round(s["tiles_y"], 4), "rotation_deg": view["rotation_deg"],
        "view": {"window": w, "centre": [round(x, 4) for x in view["centre"]],
                 "phase_yarns": view["phase_yarns"]},
        "warp": {"radius": geo["warp_radius"], "spacing": geo["warp_spacing"], "height": geo["height"],
                 "color_linear": s["warp_colour"], "count_visible": round(w / geo["warp_spacing"], 3)},
        "weft": {"radius": geo["weft_radius"], "spacing": geo["weft_spacing"], "height": geo["height"],
                 "color_linear": s["weft_colour"], "count_visible": round(w / geo["weft_spacing"], 3)},
        "color_relation": s["colour_mode"],
        "path": "interp", "crimp": geo["crimp"], "geometry": "bspline",
        "material": dict(s["material"], warp_bsdf=bsdf_dict(s["material"], s["warp_colour"]),
                         weft_bsdf=bsdf_dict(s["material"], s["weft_colour"])),
        "lights": lights, "background": background,
        "image": {"width": size, "height": size, "spp": spp, "seed": render_seed, "rfilter": "box",
                  "integrator": "path", "max_depth": 8, "exposure": round(exposure, 5)},
        "extent_world": {"W": w, "H": w},
        "timing": {"load_s": t1 - t0, "render_s": t2 - t1, "labels_s": t3 - t2},
        "name": name,
        "gt_files": {"labels_png": name + "_labels.png", "gt_npz": name + "_gt.npz"},
        "gt_coverage_mean": {"warp": float(cov[..., 0].mean()), "weft": float(cov[..., 1].mean()),
                             "background": float(cov[..., 2].mean())},
        "gt_check": {"crossings_checked": checked, "wrong": 0},
    }
    atomic_write_json(base + ".json", meta)
    return index_entry(meta)


def index_entry(meta):
    """The index.json line of one scene."""
    return {"name": meta["name"], "pattern_name": meta["pattern_name"], "pattern": meta["pattern"],
            "tiles": [meta["tiles_x"], meta["tiles_y"]], "rotation_deg": meta["rotation_deg"],
            "warp_color": meta["warp"]["color_linear"], "weft_color": meta["weft"]["color_linear"],
            "warp_radius": meta["warp"]["radius"], "weft_radius": meta["weft"]["radius"],
            "material": meta["material"]["type"], "lights": meta["lights"]["setup"],
            "background": meta["background"]["tone"], "render_s": meta["timing"]["render_s"]}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="output folder (created)")
    ap.add_argument("--count", type=int, required=True, help="number of scenes")
    ap.add_argument("--seed", type=int, required=True, help="random seed (scene k uses default_rng([seed, k]))")
    ap.add_argument("--first", type=int, default=0, help="index of the first scene (default 0)")
    ap.add_argument("--spp", type=int, default=96, help="samples per pixel (default 96)")
    ap.add_argument("--size", type=int, default=256, help="image side in pixels (default 256)")
    ap.add_argument("--variant", default="scalar_rgb",
                    help="Mitsuba variant (default scalar_rgb; llvm_ad_rgb is faster where its JIT works)")
    ap.add_argument("--dry-run", action="store_true", help="print the drawn scenes, render nothing")
    args = ap.parse_args()
    for flag in ("count", "spp", "size"):
        if getattr(args, flag) < 1:
            sys.exit(f"error: --{flag} must be at least 1 (got {getattr(args, flag)})")
    if args.first < 0 or args.seed < 0:
        sys.exit("error: --first and --seed must be non-negative")
    if args.size < 16:
        sys.exit(f"error: --size {args.size} is too small to show a pattern repeat (at least 16)")
    if args.dry_run:
        for k in range(args.first, args.first + args.count):
            s = draw_scene(args.seed, k)
            print(k, s["pattern_name"], s["pattern"].tolist(), s["tiles_x"], round(s["tiles_y"], 2),
                  s["view"]["rotation_deg"], s["geo"], s["material"]["type"], s["colour_mode"])
        return
    try:
        import mitsuba as mi
    except ImportError:
        sys.exit("error: the `mitsuba` Python package is missing (pip install mitsuba numpy; see README.md)")
    if args.variant not in mi.variants():
        sys.exit(f"error: Mitsuba variant {args.variant!r} is not available (have: {', '.join(mi.variants())})")
    mi.set_variant(args.variant)
    os.makedirs(args.out, exist_ok=True)
    workdir = tempfile.mkdtemp(prefix="woven_mitsuba_")
    for k in range(args.first, args.first + args.count):
        prefix = f"m{args.seed}_{k + 1:02d}_"
        done = [f for f in os.listdir(args.out) if f.startswith(prefix) and f.endswith(".json")]
        if done:
            print(f"scene {k}: {done[0]} exists, skipped", flush=True)
            continue
        t0 = time.monotonic()
        entry = make_scene(args.out, args.seed, k, args.size, args.spp, args.variant, workdir)
        print(f"scene {k}: {entry['name']} in {time.monotonic() - t0:.1f} s", flush=True)
    os.rmdir(workdir)
    # index.json: every scene in the folder (several runs with other seeds or ranges may share it).
    entries = []
    for f in sorted(os.listdir(args.out)):
        if f.endswith(".json") and f != "index.json" and not f.endswith(".tmp"):
            with open(os.path.join(args.out, f)) as fh:
                entries.append(index_entry(json.load(fh)))
    atomic_write_json(os.path.join(args.out, "index.json"), entries)


if __name__ == "__main__":
    main()
