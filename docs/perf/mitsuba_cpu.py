#!/usr/bin/env python3
"""Load-independent cross-check: Mitsuba 3 scalar_rgb single-thread process CPU time.

Renders scenes/cornell-box and scenes/many-lights (the XML written by
`scenes/make_scenes.py --mitsuba-xml`) at 256x256, max_depth 5, rr_depth 6 (no Russian roulette),
with one thread, and prints the best-of-N process CPU seconds of `mi.render(scene, spp=SPP)`.
Compare with cvfarm's
`cargo run --release -p render --example render_speed -- scenes/<scene>/scene.json SPP 1 N`.

Usage (repo root): python3 docs/perf/mitsuba_cpu.py [SPP] [REPEATS]   (defaults 16, 3)
"""
import os
import re
import subprocess
import sys
import tempfile
import time


def main():
    spp = int(sys.argv[1]) if len(sys.argv) > 1 else 16
    repeats = int(sys.argv[2]) if len(sys.argv) > 2 else 3
    if not os.environ.get("DRJIT_LIBLLVM_PATH"):
        out = subprocess.run(["ldconfig", "-p"], capture_output=True, text=True).stdout
        m = re.search(r"libLLVM\.so\.19\S* .*=> (\S+)", out)
        if m:
            os.environ["DRJIT_LIBLLVM_PATH"] = m.group(1)
    import drjit as dr
    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    dr.set_thread_count(1)
    tmp = tempfile.mkdtemp()
    subprocess.run([sys.executable, "scenes/make_scenes.py", "--only", "cornell-box", "--only",
                    "many-lights", "--out", f"{tmp}/native", "--mitsuba-xml", f"{tmp}/xml"],
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    for s in ["cornell-box", "many-lights"]:
        path = f"{tmp}/xml/{s}/scene.xml"
        xml = open(path).read()
        xml = re.sub(r'name="rr_depth" value="[0-9-]+"', 'name="rr_depth" value="6"', xml)
        xml = re.sub(r'name="max_depth" value="[0-9-]+"', 'name="max_depth" value="5"', xml)
        xml = re.sub(r'name="(width|height)" value="[0-9]+"', lambda m: f'name="{m.group(1)}" value="256"', xml)
        (mi.file_resolver() if hasattr(mi, "file_resolver") else mi.Thread.thread().file_resolver()).prepend(os.path.dirname(os.path.abspath(path)))
        scene = mi.load_string(xml)
        mi.render(scene, spp=1, seed=99)  # warm-up
        best = float("inf")
        for r in range(repeats):
            t0 = time.process_time()
            img = mi.render(scene, spp=spp, seed=1 + r)
            dr.eval(img)
            best = min(best, time.process_time() - t0)
        print(f"{s}: mitsuba {mi.__version__} scalar_rgb, 1 thread, {spp} spp: best CPU {best:.3f} s "
              f"(of {repeats})", flush=True)


if __name__ == "__main__":
    main()
