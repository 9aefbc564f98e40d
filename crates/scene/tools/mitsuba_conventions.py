#!/usr/bin/env python3
"""Prints the Mitsuba 3 values that crates/scene/tests/mitsuba_conventions.rs and the fov unit
test hard-code, so they can be re-checked against a Mitsuba release:

    python3 crates/scene/tools/mitsuba_conventions.py      # needs `pip install mitsuba` (3.9.1 used)

Checks: smooth vertex normals/uvs of an OBJ without `vn`, the `cube` shape's vertices under a
transform, checkerboard parity and `to_uv`, bitmap orientation, `x_fov` for fov_axis y/diagonal
and focal_length, and the default `conductor` eta/k.
"""
import math
import os
import tempfile

import mitsuba as mi
import numpy as np

mi.set_variant("scalar_rgb")
tmp = tempfile.mkdtemp()

PYRAMID = """v 0 0 0\nv 2 0 0\nv 2 0 1\nv 0 0 1\nv 0.5 1 0.3\nvt 0 0\nvt 1 0\nvt 1 1
f 1/1 2/2 5/3\nf 2/2 3/3 5/3\nf 3/1 4/2 5/3\nf 4/1 1/2 5/3\nf 1 4 3 2\n"""
with open(os.path.join(tmp, "pyr.obj"), "w") as f:
    f.write(PYRAMID)
shape = mi.load_dict({"type": "obj", "filename": os.path.join(tmp, "pyr.obj"),
                      "to_world": mi.ScalarTransform4f().scale([1, 2, 1])})
p = mi.traverse(shape)
print("pyramid normals:\n", np.array(p["vertex_normals"]).reshape(-1, 3))
print("pyramid uvs:\n", np.array(p["vertex_texcoords"]).reshape(-1, 2))

cube = mi.load_dict({"type": "cube", "to_world": mi.ScalarTransform4f().translate([-0.4, 0.3, -0.3])
                     @ mi.ScalarTransform4f().rotate([0, 1, 0], 20) @ mi.ScalarTransform4f().scale(0.3)})
print("cube first vertices:\n", np.array(mi.traverse(cube)["vertex_positions"]).reshape(-1, 3)[:4])


def ev(t, u, v):
    si = mi.SurfaceInteraction3f()
    si.uv = mi.Point2f(u, v)
    return t.eval(si)


probes = [(0.1, 0.1), (0.6, 0.1), (0.1, 0.6), (0.6, 0.6), (0.3, 0.1)]
for op in ["", '<translate x="0.5"/>', '<rotate z="1" angle="90"/>', '<scale x="2" y="2"/>']:
    t = mi.load_string(f'<texture version="3.0.0" type="checkerboard"><float name="color0" value="0.9"/>'
                       f'<float name="color1" value="0.1"/><transform name="to_uv">{op}</transform></texture>')
    print("checkerboard", repr(op), [round(ev(t, u, v)[0], 2) for u, v in probes])

img = np.array([[[1, 0, 0], [0, 1, 0]], [[0, 0, 1], [1, 1, 1]]], dtype=np.float32)
mi.Bitmap(img).write(os.path.join(tmp, "quad.exr"))
t = mi.load_dict({"type": "bitmap", "filename": os.path.join(tmp, "quad.exr"), "filter_type": "nearest"})
print("bitmap", [(uv, list(ev(t, *uv))) for uv in [(0.25, 0.25), (0.75, 0.25), (0.25, 0.75)]])

film = {"type": "hdrfilm", "width": 300, "height": 200}
for extra in [{"fov": 30, "fov_axis": "y"}, {"fov": 30, "fov_axis": "diagonal"}, {"focal_length": "35mm"}]:
    s = mi.load_dict({"type": "perspective", "film": film, **extra})
    print("x_fov", extra, mi.traverse(s)["x_fov"])
print("35mm expected", math.degrees(2 * math.atan(18 / 35)))
c = mi.traverse(mi.load_dict({"type": "conductor"}))
print("default conductor eta, k:", c["eta.value"], c["k.value"])
