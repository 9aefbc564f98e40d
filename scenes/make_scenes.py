#!/usr/bin/env python3
"""Generate cvfarm's shipped example scenes (native JSON, see crates/scene/src/desc.rs).

Usage (from the repository root):
  python3 scenes/make_scenes.py                      # (re)write scenes/<name>/scene.json for every scene
  python3 scenes/make_scenes.py --only checkers      # one scene
  python3 scenes/make_scenes.py --mitsuba-xml DIR    # also write DIR/<name>/scene.xml: the same scene in
                                                     # Mitsuba 3 XML (inline meshes as OBJ), for rendering
                                                     # it with Mitsuba as a peer / for previews
  python3 scenes/make_scenes.py --cbox-dir PATH      # where the Cornell box OBJs are read from
  python3 scenes/make_scenes.py --veach-triangles F  # write F: scenes/veach-mis/scene.json with every
                                                     # sphere lamp as 36 x 36 triangles, each an emitter of
                                                     # its own (10 080 lights; ~3 MB, not shipped), as the
                                                     # paper's variant of the scene [Hua §7.3]

Everything is deterministic (fixed seeds), so running the script again reproduces the files
byte for byte. Only the Python standard library is needed.

Scenes (provenance in scenes/README.md):
  cornell-box  the classic Cornell box (mitsuba-data cbox geometry, in mm), one-sided diffuse
  veach-mis    4 glossy plates of increasing roughness, 4 sphere lights of equal power
  many-lights  room with 8 x 8 = 64 small coloured quad lights, glossy objects
  envmap       diffuse plane + glossy spheres under the museum.exr environment map
  colour-lamp  red, green and blue lamps of equal luminance over white/glossy objects
  checkers     Fan et al. 2006's scene: glossy checkerboard plane, large yellow + small blue light
"""
import argparse
import json
import math
import os
import random
import shutil
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_CBOX = "/work/shared/scenes-mitsuba/cbox/meshes"
DEFAULT_MUSEUM = "/work/shared/scenes-mitsuba/bsdf-spheres/roughplastic-ggx/museum.exr"

# Rec. 709 luminance weights (linear RGB).
LUM = (0.2126, 0.7152, 0.0722)


def r6(x):
    """Round to 6 significant digits so that the JSON stays short and stable."""
    if isinstance(x, (list, tuple)):
        return [r6(v) for v in x]
    if isinstance(x, float):
        if x == 0.0:
            return 0.0
        v = float("%.6g" % x)
        return int(v) if v == int(v) and abs(v) < 1e9 else v
    return x


def camera(origin, target, fov, up=(0, 1, 0), fov_axis="x", near=0.01, far=10000.0):
    cam = {"fov": fov, "fov_axis": fov_axis,
           "transform": [{"look_at": {"origin": r6(list(origin)), "target": r6(list(target)), "up": list(up)}}]}
    if near != 0.01:
        cam["near_clip"] = near
    if far != 10000.0:
        cam["far_clip"] = far
    return cam


def rect(material, scale, rotations, translate, emitter=None):
    """A `rectangle` shape: the [-1,1]^2 square (normal +Z) scaled, rotated (list of (axis, deg)), moved."""
    t = [{"scale": r6(list(scale))}]
    for axis, angle in rotations:
        t.append({"rotate": {"axis": list(axis), "angle": r6(angle)}})
    t.append({"translate": r6(list(translate))})
    s = {"type": "rectangle", "material": material, "transform": t}
    if emitter is not None:
        s["emitter"] = {"radiance": r6(list(emitter))}
    return s


def sub(a, b):
    return [a[i] - b[i] for i in range(3)]


def add(a, b):
    return [a[i] + b[i] for i in range(3)]


def mul(a, s):
    return [v * s for v in a]


def norm(a):
    n = math.sqrt(sum(v * v for v in a))
    return [v / n for v in a]


def cross(a, b):
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def dot(a, b):
    return sum(a[i] * b[i] for i in range(3))


def facing_rotations(n):
    """Rotations (axis, degrees) that turn +Z into the unit vector n: tilt about X, then turn about Y."""
    # +Z --rotate about X by a--> (0, -sin a, cos a); then about Y by b --> (cos a sin b, -sin a, cos a cos b)
    a = math.degrees(math.asin(max(-1.0, min(1.0, -n[1]))))
    b = math.degrees(math.atan2(n[0], n[2]))
    return [((1, 0, 0), a), ((0, 1, 0), b)]


# --------------------------------------------------------------------------------------------
# cornell-box


def read_obj(path):
    """Positions and faces (fan-triangulated) of a simple OBJ; normals/uvs are not referenced by
    the cbox faces, so they are ignored (face normals, as Mitsuba renders these files)."""
    pos, tris = [], []
    with open(path) as fh:
        for line in fh:
            p = line.split()
            if not p:
                continue
            if p[0] == "v":
                pos.append([float(v) for v in p[1:4]])
            elif p[0] == "f":
                idx = [int(v.split("/")[0]) - 1 for v in p[1:]]
                for k in range(1, len(idx) - 1):
                    tris.append([idx[0], idx[k], idx[k + 1]])
    used = sorted({i for t in tris for i in t})
    remap = {old: new for new, old in enumerate(used)}
    return [pos[i] for i in used], [[remap[i] for i in t] for t in tris]


def cornell_box(cbox_dir):
    mats = {
        "box": {"type": "diffuse", "reflectance": [0.45, 0.30, 0.90]},
        "white": {"type": "diffuse", "reflectance": [0.885809, 0.698859, 0.666422]},
        "red": {"type": "diffuse", "reflectance": [0.570068, 0.0430135, 0.0443706]},
        "green": {"type": "diffuse", "reflectance": [0.105421, 0.37798, 0.076425]},
        "light": {"type": "diffuse", "reflectance": [0.936461, 0.740433, 0.705267]},
    }
    shapes = []
    for name, mat in [("luminaire", "light"), ("floor", "white"), ("ceiling", "white"), ("back", "white"),
                      ("greenwall", "green"), ("redwall", "red"), ("smallbox", "box"), ("largebox", "box")]:
        pos, tris = read_obj(os.path.join(cbox_dir, f"cbox_{name}.obj"))
        s = {"type": "mesh", "positions": r6(pos), "indices": tris, "material": mat}
        if name == "luminaire":
            s["transform"] = [{"translate": [0, -0.5, 0]}]
            s["emitter"] = {"radiance": [18.387, 10.9873, 2.75357]}
        shapes.append(s)
    return {
        "camera": camera((278, 273, -800), (278, 273, -799), 39.3077, fov_axis="smaller", near=10.0, far=2800.0),
        "film": {"width": 256, "height": 256},
        "integrator": {"max_depth": 5, "rr_depth": 5},
        "materials": mats,
        "shapes": shapes,
    }


# --------------------------------------------------------------------------------------------
# veach-mis


def segments_cross(p0, p1, q0, q1):
    """Whether 2-D segments p0p1 and q0q1 properly intersect."""
    def side(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])
    return side(p0, p1, q0) * side(p0, p1, q1) < 0 and side(q0, q1, p0) * side(q0, q1, p1) < 0


def veach_mis():
    """Veach's MIS test scene (thesis fig. 9.2), rebuilt from its description: 4 sphere lights in
    a row (radii 0.0333…0.9, radiance ∝ 1/r² so that all have the same power, as in the widely
    used version of the scene) above 4 rough-conductor plates. The plates are placed by us: each
    one is tilted so that the camera sees the mirror images of the lights in its middle, they
    are spaced so that no plate shadows another (checked below), and roughness grows from the
    front plate to the back one."""
    cam_o, cam_t = [0.0, 6.0, 27.5], [0.0, -0.3, 2.5]
    fov = 28.0
    radii = [0.03333, 0.1, 0.3, 0.9]
    xs = [-3.75, -1.25, 1.25, 3.75]
    light_y = 2.5  # the row of lights: y = light_y, z = 0
    mats = {
        "backdrop": {"type": "diffuse", "reflectance": [0.4, 0.4, 0.4]},
        "lamp": {"type": "diffuse", "reflectance": 0.0},
    }
    alphas = [0.2, 0.08, 0.03, 0.008]  # back plate (highest in the image) is the roughest
    zs = [1.0, 4.0, 7.0, 10.0]
    depression = [11.0, 14.5, 18.0, 21.5]  # degrees below the camera's horizon of each plate centre
    half_depth = 0.7
    shapes, profile = [], []
    for i, (z, dep, a) in enumerate(zip(zs, depression, alphas)):
        c = [0.0, cam_o[1] - (cam_o[2] - z) * math.tan(math.radians(dep)), z]
        n = norm(add(norm(sub(cam_o, c)), norm(sub([0.0, light_y, 0.0], c))))
        t = [n[2], -n[1]]  # plate direction in the (y, z) plane
        profile.append(((c[1] - half_depth * t[0], c[2] - half_depth * t[1]),
                        (c[1] + half_depth * t[0], c[2] + half_depth * t[1])))
        mats[f"plate{i}"] = {"type": "roughconductor", "distribution": "ggx", "alpha": a,
                             "eta": [0.200438, 0.924033, 1.10221], "k": [3.91295, 2.45285, 2.14219]}
        shapes.append(rect(f"plate{i}", (4.5, half_depth, 1.0), facing_rotations(n), c))
    # no plate may shadow another from any part of the light row (checked in the (y, z) plane)
    for i, (p0, p1) in enumerate(profile):
        for k in range(11):
            p = (p0[0] + (p1[0] - p0[0]) * k / 10, p0[1] + (p1[1] - p0[1]) * k / 10)
            for ly in (light_y - 0.9, light_y, light_y + 0.9):
                for j, (q0, q1) in enumerate(profile):
                    assert j == i or not segments_cross(p, (ly, 0.0), q0, q1), f"plate {j} shadows plate {i}"
    # Backdrop: a floor below the plates and a wall behind the lights, dim diffuse.
    shapes.append(rect("backdrop", (12, 12, 1), [((1, 0, 0), -90)], (0, -4.0, 4.0)))
    shapes.append(rect("backdrop", (12, 10, 1), [], (0, 4.0, -3.0)))
    base_power = 100.0 * 0.1 ** 2  # radiance 100 at r = 0.1, as in Veach's scene
    for x, r in zip(xs, radii):
        shapes.append({"type": "sphere", "center": [x, light_y, 0], "radius": r,
                       "material": "lamp", "emitter": {"radiance": r6([base_power / (r * r)] * 3)}})
    return {
        "camera": camera(cam_o, cam_t, fov),
        "film": {"width": 384, "height": 256},
        "integrator": {"max_depth": 5, "rr_depth": 5},
        "materials": mats,
        "shapes": shapes,
    }


# --------------------------------------------------------------------------------------------
# many-lights


def room(mats, shapes, left=(0.63, 0.065, 0.05), right=(0.14, 0.45, 0.091), white=(0.725, 0.71, 0.68)):
    """Cornell-style room [-1,1] x [0,2] x [-1,1] (y up, open towards +z), twosided diffuse walls."""
    for name, col in [("white", white), ("left", left), ("right", right)]:
        mats[name] = {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": list(col)}}
    shapes.append(rect("white", (1, 1, 1), [((1, 0, 0), -90)], (0, 0, 0)))   # floor, faces +y
    shapes.append(rect("white", (1, 1, 1), [((1, 0, 0), 90)], (0, 2, 0)))    # ceiling, faces -y
    shapes.append(rect("white", (1, 1, 1), [], (0, 1, -1)))                   # back, faces +z
    shapes.append(rect("left", (1, 1, 1), [((0, 1, 0), 90)], (-1, 1, 0)))     # left, faces +x
    shapes.append(rect("right", (1, 1, 1), [((0, 1, 0), -90)], (1, 1, 0)))    # right, faces -x


def many_lights(n=8, seed=1, res=256):
    rng = random.Random(seed)
    mats, shapes = {}, []
    room(mats, shapes)
    mats["lamp"] = {"type": "diffuse", "reflectance": 0.0}
    mats["gold"] = {"type": "roughconductor", "distribution": "ggx", "alpha": 0.15,
                    "eta": [0.143119, 0.374957, 1.44248], "k": [3.98316, 2.38572, 1.60322]}
    mats["blue-plastic"] = {"type": "roughplastic", "distribution": "ggx", "alpha": 0.1, "int_ior": 1.5,
                            "ext_ior": 1.0, "diffuse_reflectance": [0.1, 0.3, 0.6]}
    mats["steel"] = {"type": "roughconductor", "distribution": "ggx", "alpha": 0.05,
                     "eta": [2.86, 2.57, 2.27], "k": [3.1, 2.86, 2.6]}
    shapes.append({"type": "cube", "material": "gold",
                   "transform": [{"scale": [0.3, 0.3, 0.3]}, {"rotate": {"axis": [0, 1, 0], "angle": 20}},
                                 {"translate": [-0.4, 0.3, -0.3]}]})
    shapes.append({"type": "cube", "material": "blue-plastic",
                   "transform": [{"scale": [0.25, 0.25, 0.25]}, {"rotate": {"axis": [0, 1, 0], "angle": -25}},
                                 {"translate": [0.45, 0.25, 0.2]}]})
    shapes.append({"type": "sphere", "center": [0.1, 0.2, 0.55], "radius": 0.2, "material": "steel"})
    half = 0.03
    for i in range(n):
        for j in range(n):
            x = -0.85 + 1.7 * (i + 0.5) / n
            z = -0.85 + 1.7 * (j + 0.5) / n
            c = [rng.uniform(0.05, 1.0) for _ in range(3)]
            scale = rng.choice([5.0, 20.0, 80.0])
            shapes.append(rect("lamp", (half, half, 1), [((1, 0, 0), 90)], (x, 1.999, z),
                               emitter=[scale * v for v in c]))
    return {
        "camera": camera((0, 1, 3.9), (0, 1, 0), 39.3),
        "film": {"width": res, "height": res},
        "integrator": {"max_depth": 5, "rr_depth": 5},
        "materials": mats,
        "shapes": shapes,
    }


# --------------------------------------------------------------------------------------------
# envmap


def envmap():
    mats = {
        "ground": {"type": "diffuse", "reflectance": [0.5, 0.5, 0.5]},
        "copper": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.08,
                   "eta": [0.200438, 0.924033, 1.10221], "k": [3.91295, 2.45285, 2.14219]},
        "plastic": {"type": "roughplastic", "distribution": "ggx", "alpha": 0.2, "int_ior": 1.5046,
                    "diffuse_reflectance": [0.6, 0.05, 0.05]},
    }
    shapes = [
        rect("ground", (6, 6, 1), [((1, 0, 0), -90)], (0, 0, 0)),
        {"type": "sphere", "center": [-1.1, 1.0, 0.0], "radius": 1.0, "material": "copper"},
        {"type": "sphere", "center": [1.1, 0.7, 0.5], "radius": 0.7, "material": "plastic"},
    ]
    return {
        "camera": camera((0, 2.2, 6.5), (0, 0.8, 0), 45.0),
        "film": {"width": 320, "height": 240},
        "integrator": {"max_depth": 5, "rr_depth": 5},
        "materials": mats,
        "shapes": shapes,
        "environment": {"type": "envmap", "filename": "museum.exr", "scale": 1.0},
    }


# --------------------------------------------------------------------------------------------
# colour-lamp


def colour_lamp(luminance=6.0):
    """Three lamps of equal luminance Y = 0.2126 R + 0.7152 G + 0.0722 B but saturated, very
    different colours: selecting lights by luminance picks each equally often although their
    per-channel contributions differ by up to ~10x (a test for mono vs RGB CV coefficients)."""
    mats, shapes = {}, []
    room(mats, shapes, left=(0.725, 0.71, 0.68), right=(0.725, 0.71, 0.68))
    mats["lamp"] = {"type": "diffuse", "reflectance": 0.0}
    mats["glossy"] = {"type": "roughplastic", "distribution": "ggx", "alpha": 0.05, "int_ior": 1.5,
                      "diffuse_reflectance": [0.8, 0.8, 0.8]}
    mats["chrome"] = {"type": "roughconductor", "distribution": "ggx", "alpha": 0.2}
    colours = [(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)]
    for k, col in enumerate(colours):
        y = sum(LUM[c] * col[c] for c in range(3))
        rad = [luminance * v / y for v in col]
        x = -0.55 + 0.55 * k
        shapes.append(rect("lamp", (0.12, 0.12, 1), [((1, 0, 0), 90)], (x, 1.999, -0.1), emitter=rad))
    shapes.append({"type": "sphere", "center": [-0.45, 0.35, -0.2], "radius": 0.35, "material": "glossy"})
    shapes.append({"type": "sphere", "center": [0.45, 0.3, 0.25], "radius": 0.3, "material": "chrome"})
    return {
        "camera": camera((0, 1, 3.9), (0, 1, 0), 39.3),
        "film": {"width": 256, "height": 256},
        "integrator": {"max_depth": 5, "rr_depth": 5},
        "materials": mats,
        "shapes": shapes,
    }


# --------------------------------------------------------------------------------------------
# checkers


def checkers():
    """Fan et al. 2006, fig. 2 (after pbrt's direct-lighting scene): a glossy checkerboard plane,
    a large yellow and a small blue area light of similar power; max_depth 2 (direct lighting)."""
    mats = {
        "checks": {"type": "roughplastic", "distribution": "ggx", "alpha": 0.06, "int_ior": 1.5,
                   "diffuse_reflectance": {"texture": "board"}},
        "lamp": {"type": "diffuse", "reflectance": 0.0},
    }
    textures = {"board": {"type": "checkerboard", "color0": [0.6, 0.6, 0.6], "color1": [0.05, 0.05, 0.05],
                          "uv_transform": [{"scale": [8, 8, 1]}]}}
    shapes = [rect("checks", (4, 4, 1), [((1, 0, 0), -90)], (0, 0, 0))]
    # Lights hang above the far half of the plane and face the camera side of the plane.
    for centre, size, rad in [((-1.4, 1.6, -1.8), 0.9, (10.0, 8.0, 1.0)),
                              ((1.5, 1.2, -1.4), 0.15, (8.0, 24.0, 190.0))]:
        n = norm(sub([0.0, 0.0, 0.8], list(centre)))
        shapes.append(rect("lamp", (size, size, 1), facing_rotations(n), centre, emitter=rad))
    return {
        "camera": camera((0, 2.6, 5.0), (0, 0.2, -0.6), 45.0),
        "film": {"width": 320, "height": 240},
        "integrator": {"max_depth": 2, "rr_depth": 5},
        "textures": textures,
        "materials": mats,
        "shapes": shapes,
    }


# --------------------------------------------------------------------------------------------
# output


def dumps(doc, width=100):
    """Readable JSON: a value that fits in `width` columns stays on one line, else it is broken up."""
    def one_line(v):
        return json.dumps(v, ensure_ascii=False, separators=(", ", ": "))

    def go(v, indent):
        flat = one_line(v)
        if len(flat) + indent <= width or not isinstance(v, (dict, list)) or not v:
            return flat
        pad = " " * (indent + 2)
        if isinstance(v, dict):
            items = [f"{pad}{json.dumps(k)}: {go(x, indent + 2)}" for k, x in v.items()]
            return "{\n" + ",\n".join(items) + "\n" + " " * indent + "}"
        items = [pad + go(x, indent + 2) for x in v]
        return "[\n" + ",\n".join(items) + "\n" + " " * indent + "]"

    return go(doc, 0) + "\n"


# ---- Mitsuba 3 XML export (peer renders / previews) -----------------------------------------


def fmt(v):
    return ", ".join("%.9g" % x for x in v)


def xml_transform(ops, indent):
    out = [f'{indent}<transform name="to_world">']
    for op in ops:
        (k, v), = op.items()
        if k == "translate":
            out.append(f'{indent}  <translate x="{v[0]}" y="{v[1]}" z="{v[2]}"/>')
        elif k == "scale":
            out.append(f'{indent}  <scale x="{v[0]}" y="{v[1]}" z="{v[2]}"/>')
        elif k == "rotate":
            a = v["axis"]
            out.append(f'{indent}  <rotate x="{a[0]}" y="{a[1]}" z="{a[2]}" angle="{v["angle"]}"/>')
        elif k == "look_at":
            out.append(f'{indent}  <lookat origin="{fmt(v["origin"])}" target="{fmt(v["target"])}" up="{fmt(v["up"])}"/>')
        elif k == "matrix":
            out.append(f'{indent}  <matrix value="{" ".join(str(x) for x in v)}"/>')
    out.append(f"{indent}</transform>")
    return out


def xml_color(name, c, textures, indent):
    if isinstance(c, dict):
        t = textures[c["texture"]]
        out = [f'{indent}<texture type="checkerboard" name="{name}">',
               f'{indent}  <rgb name="color0" value="{fmt(t["color0"])}"/>',
               f'{indent}  <rgb name="color1" value="{fmt(t["color1"])}"/>']
        if t.get("uv_transform"):
            m = xml_transform(t["uv_transform"], indent + "  ")
            m[0] = m[0].replace('name="to_world"', 'name="to_uv"')
            out += m
        return out + [f"{indent}</texture>"]
    if isinstance(c, (int, float)):
        c = [c] * 3
    return [f'{indent}<rgb name="{name}" value="{fmt(c)}"/>']


def xml_bsdf(m, textures, indent):
    t = m["type"]
    if t == "twosided":
        return [f'{indent}<bsdf type="twosided">'] + xml_bsdf(m["bsdf"], textures, indent + "  ") + [f"{indent}</bsdf>"]
    out = [f'{indent}<bsdf type="{t}">']
    i2 = indent + "  "
    if t == "diffuse":
        out += xml_color("reflectance", m.get("reflectance", 0.5), textures, i2)
    elif t in ("roughconductor", "conductor"):
        if t == "roughconductor":
            out.append(f'{i2}<string name="distribution" value="{m.get("distribution", "ggx")}"/>')
            out.append(f'{i2}<float name="alpha" value="{m.get("alpha", 0.1)}"/>')
        out.append(f'{i2}<rgb name="eta" value="{fmt(m.get("eta", [1.65746, 0.880369, 0.521229]))}"/>')
        out.append(f'{i2}<rgb name="k" value="{fmt(m.get("k", [9.223869, 6.269523, 4.837001]))}"/>')
    elif t == "roughplastic":
        out.append(f'{i2}<string name="distribution" value="{m.get("distribution", "ggx")}"/>')
        out.append(f'{i2}<float name="alpha" value="{m.get("alpha", 0.1)}"/>')
        out.append(f'{i2}<float name="int_ior" value="{m.get("int_ior", 1.49)}"/>')
        out.append(f'{i2}<float name="ext_ior" value="{m.get("ext_ior", 1.000277)}"/>')
        out += xml_color("diffuse_reflectance", m.get("diffuse_reflectance", 0.5), textures, i2)
    return out + [f"{indent}</bsdf>"]


def write_obj(path, pos, tris):
    with open(path, "w") as fh:
        for p in pos:
            fh.write("v %.9g %.9g %.9g\n" % tuple(p))
        for t in tris:
            fh.write("f %d %d %d\n" % (t[0] + 1, t[1] + 1, t[2] + 1))


def to_mitsuba(doc, out_dir, assets):
    """Write the scene as Mitsuba 3 XML (same camera, film, integrator, box filter)."""
    os.makedirs(out_dir, exist_ok=True)
    cam, film = doc["camera"], doc["film"]
    integ = doc.get("integrator", {})
    x = ['<scene version="3.0.0">',
         f'  <integrator type="path"><integer name="max_depth" value="{integ.get("max_depth", 5)}"/>'
         f'<integer name="rr_depth" value="{integ.get("rr_depth", 5)}"/></integrator>',
         '  <sensor type="perspective">',
         f'    <string name="fov_axis" value="{cam.get("fov_axis", "x")}"/>',
         f'    <float name="fov" value="{cam["fov"]}"/>',
         f'    <float name="near_clip" value="{cam.get("near_clip", 0.01)}"/>',
         f'    <float name="far_clip" value="{cam.get("far_clip", 10000.0)}"/>']
    x += xml_transform(cam["transform"], "    ")
    x += ['    <sampler type="independent"><integer name="sample_count" value="64"/></sampler>',
          f'    <film type="hdrfilm"><integer name="width" value="{film["width"]}"/>'
          f'<integer name="height" value="{film["height"]}"/><rfilter type="box"/>'
          '<string name="pixel_format" value="rgb"/></film>',
          '  </sensor>']
    mats, textures = doc.get("materials", {}), doc.get("textures", {})
    for i, s in enumerate(doc["shapes"]):
        t = s["type"]
        if t == "mesh":
            fn = f"mesh_{i}.obj"
            write_obj(os.path.join(out_dir, fn), s["positions"], s["indices"])
            x.append('  <shape type="obj">')
            x.append(f'    <string name="filename" value="{fn}"/>')
        elif t == "sphere":
            x.append('  <shape type="sphere">')
            x.append(f'    <point name="center" value="{fmt(s.get("center", [0, 0, 0]))}"/>')
            x.append(f'    <float name="radius" value="{s.get("radius", 1.0)}"/>')
        else:
            x.append(f'  <shape type="{t}">')
        if s.get("transform"):
            x += xml_transform(s["transform"], "    ")
        m = s.get("material", {"type": "diffuse"})
        x += xml_bsdf(mats[m] if isinstance(m, str) else m, textures, "    ")
        if "emitter" in s:
            x.append(f'    <emitter type="area"><rgb name="radiance" value="{fmt(s["emitter"]["radiance"])}"/></emitter>')
        x.append("  </shape>")
    env = doc.get("environment")
    if env and env["type"] == "envmap":
        x.append(f'  <emitter type="envmap"><string name="filename" value="{env["filename"]}"/>'
                 f'<float name="scale" value="{env.get("scale", 1.0)}"/></emitter>')
        for a in assets:
            shutil.copyfile(a, os.path.join(out_dir, os.path.basename(a)))
    elif env and env["type"] == "constant":
        x.append(f'  <emitter type="constant"><rgb name="radiance" value="{fmt(env["radiance"])}"/></emitter>')
    x.append("</scene>")
    with open(os.path.join(out_dir, "scene.xml"), "w") as fh:
        fh.write("\n".join(x) + "\n")


def veach_triangle_lamps(src, stacks=36, slices=36):
    """The scene `src` (a loaded JSON doc) with every sphere lamp tessellated: `stacks x slices`
    quads (triangles at the poles), each triangle a shape and so an emitter of its own."""
    shapes = []
    for s in src["shapes"]:
        if s["type"] != "sphere":
            shapes.append(s)
            continue
        c, r = s["center"], s["radius"]
        pos = []
        for i in range(stacks + 1):
            th = math.pi * i / stacks
            for j in range(slices):
                ph = 2 * math.pi * j / slices
                d = (math.sin(th) * math.cos(ph), math.cos(th), math.sin(th) * math.sin(ph))
                pos.append([c[k] + r * d[k] for k in range(3)])
        for i in range(stacks):
            for j in range(slices):
                a, b = i * slices + j, i * slices + (j + 1) % slices
                e, f = (i + 1) * slices + j, (i + 1) * slices + (j + 1) % slices
                # Counter-clockwise seen from outside: the emitting side faces out.
                tris = ([[a, b, e]] if i > 0 else []) + ([[b, f, e]] if i < stacks - 1 else [])
                for t in tris:
                    shapes.append({"type": "mesh", "material": s["material"], "emitter": s["emitter"],
                                   "positions": [pos[k] for k in t], "indices": [[0, 1, 2]]})
    out = dict(src)
    out["shapes"] = shapes
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", action="append", help="generate only this scene (repeatable)")
    ap.add_argument("--out", default=HERE, help="output root (default: the scenes/ directory)")
    ap.add_argument("--cbox-dir", default=DEFAULT_CBOX, help="directory with the cbox_*.obj files")
    ap.add_argument("--museum", default=DEFAULT_MUSEUM, help="museum.exr (copied into envmap/ if missing)")
    ap.add_argument("--mitsuba-xml", default=None, help="also write Mitsuba 3 XML versions under this directory")
    ap.add_argument("--veach-triangles", default=None,
                    help="write veach-mis with triangle lamps (10 080 emitters) to this file and exit")
    a = ap.parse_args()
    if a.veach_triangles:
        with open(os.path.join(a.out, "veach-mis", "scene.json")) as fh:
            doc = veach_triangle_lamps(json.load(fh))
        with open(a.veach_triangles, "w") as fh:
            json.dump(doc, fh)
        print(f"wrote {a.veach_triangles}", file=sys.stderr)
        return 0
    builders = {
        "cornell-box": lambda: (cornell_box(a.cbox_dir), []),
        "veach-mis": lambda: (veach_mis(), []),
        "many-lights": lambda: (many_lights(), []),
        "many-lights-256": lambda: (many_lights(16, seed=2, res=128), []),
        "envmap": lambda: (envmap(), ["museum.exr"]),
        "colour-lamp": lambda: (colour_lamp(), []),
        "checkers": lambda: (checkers(), []),
    }
    for name, build in builders.items():
        if a.only and name not in a.only:
            continue
        doc, assets = build()
        d = os.path.join(a.out, name)
        os.makedirs(d, exist_ok=True)
        for asset in assets:
            dst = os.path.join(d, asset)
            if not os.path.exists(dst):
                shutil.copyfile(a.museum, dst)
        with open(os.path.join(d, "scene.json"), "w") as fh:
            fh.write(dumps(doc))
        print(f"wrote {os.path.join(d, 'scene.json')}", file=sys.stderr)
        if a.mitsuba_xml:
            to_mitsuba(doc, os.path.join(a.mitsuba_xml, name), [os.path.join(d, x) for x in assets])
    return 0


if __name__ == "__main__":
    sys.exit(main())
