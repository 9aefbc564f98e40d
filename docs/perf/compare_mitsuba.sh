#!/bin/sh
# Renderer speed vs Mitsuba 3 at equal spp on the same machine (DESIGN §8).
#
# Scenes: scenes/cornell-box and scenes/many-lights (native JSON for cvfarm; the identical Mitsuba
# 3 XML written by `scenes/make_scenes.py --mitsuba-xml` for Mitsuba), 256x256, max_depth 5,
# rr_depth 6 (no Russian roulette in either renderer), 2 threads, path integrator, box filter.
# Mitsuba variants scalar_rgb and llvm_ad_rgb; in each Mitsuba process a cold render comes first and
# the timed renders follow (so llvm's JIT compilation is not counted; the cold time is listed too).
# cvfarm reports rays/s too (camera + shadow + continuation rays); Mitsuba does not count rays.
# Every timed render is repeated REPEATS times (default 3) and the fastest counts, for both
# renderers alike: on a shared machine the minimum is the least disturbed run.
#
# Usage (repo root): [REPEATS=n] sh docs/perf/compare_mitsuba.sh [SPP]      (default SPP 64)
# The CLI is built (and run) in $CARGO_TARGET_DIR when set, else ./target.
# Writes docs/perf/mitsuba.md and docs/perf/mitsuba.json.
set -e
SPP=${1:-64}
THREADS=2
RES=256
REPEATS=${REPEATS:-3}
ROOT=$(pwd)
TMP=$(mktemp -d)
OUT_MD=$ROOT/docs/perf/mitsuba.md
OUT_JSON=$ROOT/docs/perf/mitsuba.json
if [ -z "$DRJIT_LIBLLVM_PATH" ]; then
  DRJIT_LIBLLVM_PATH=$(ldconfig -p | sed -n 's/.*libLLVM\.so\.19[^ ]* .*=> //p' | head -n1)
  export DRJIT_LIBLLVM_PATH
fi

cargo build --release -p cli >&2
LOAD_START=$(cut -d' ' -f1-3 /proc/loadavg)
CVFARM=${CARGO_TARGET_DIR:-$ROOT/target}/release/cvfarm
python3 scenes/make_scenes.py --only cornell-box --only many-lights --out "$TMP/native" \
  --mitsuba-xml "$TMP/xml" 2>/dev/null

for s in cornell-box many-lights; do
  r=1
  while [ $r -le "$REPEATS" ]; do
    "$CVFARM" render "scenes/$s/scene.json" --res ${RES}x${RES} --spp "$SPP" --max-depth 5 --rr-depth 6 \
      --threads $THREADS --seed 1 -o "$TMP/$s.cvfarm.exr" --stats "$TMP/$s.cvfarm.$r.json" >&2
    r=$((r + 1))
  done
  for v in scalar_rgb llvm_ad_rgb; do
    python3 - "$TMP/xml/$s/scene.xml" "$v" "$SPP" "$THREADS" "$RES" "$TMP/$s.$v.exr" "$TMP/$s.$v.json" "$REPEATS" <<'PY'
import json, sys, time
scene_path, variant, spp, threads, res, exr, out, repeats = sys.argv[1:9]
spp, threads, res, repeats = int(spp), int(threads), int(res), int(repeats)
import os, re
import mitsuba as mi
import drjit as dr
mi.set_variant(variant)
dr.set_thread_count(threads)
t0 = time.perf_counter()
xml = open(scene_path).read()
xml = re.sub(r'name="rr_depth" value="[0-9-]+"', 'name="rr_depth" value="6"', xml)
xml = re.sub(r'name="max_depth" value="[0-9-]+"', 'name="max_depth" value="5"', xml)
xml = re.sub(r'name="(width|height)" value="[0-9]+"', lambda m: f'name="{m.group(1)}" value="{res}"', xml)
(mi.file_resolver() if hasattr(mi, "file_resolver") else mi.Thread.thread().file_resolver()).prepend(os.path.dirname(os.path.abspath(scene_path)))
scene = mi.load_string(xml)
load_s = time.perf_counter() - t0
t1 = time.perf_counter()
img = mi.render(scene, spp=spp, seed=99)
dr.eval(img); dr.sync_thread()
cold_s = time.perf_counter() - t1
secs = float("inf")
for _ in range(repeats):
    t2 = time.perf_counter()
    img = mi.render(scene, spp=spp, seed=1)
    dr.eval(img); dr.sync_thread()
    secs = min(secs, time.perf_counter() - t2)
mi.Bitmap(img).write(exr)
import numpy as np
pixels = np.array(img)
mean = pixels.reshape(-1, pixels.shape[-1])[:, :3].astype(np.float64).mean(axis=0).tolist()
json.dump({"variant": variant, "seconds": secs, "cold_seconds": cold_s, "load_seconds": load_s,
           "samples": res * res * spp, "samples_per_s": res * res * spp / secs, "mean": mean}, open(out, "w"))
PY
  done
done

LOAD_END=$(cut -d' ' -f1-3 /proc/loadavg)
python3 - "$TMP" "$SPP" "$THREADS" "$RES" "$OUT_MD" "$OUT_JSON" "$LOAD_START" "$LOAD_END" "$REPEATS" <<'PY'
import json, os, platform, subprocess, sys, datetime
tmp, spp, threads, res, out_md, out_json, load_start, load_end, repeats = sys.argv[1:10]
rows, doc = [], {"spp": int(spp), "load_average_start": load_start, "load_average_end": load_end, "repeats": int(repeats), "threads": int(threads), "resolution": [int(res)] * 2, "max_depth": 5,
                 "rr_depth": 6, "entries": []}
cpu = "unknown"
try:
    cpu = [l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo") if l.startswith("model name")][0]
except Exception:
    pass
import mitsuba
for s in ["cornell-box", "many-lights"]:
    runs = [json.load(open(os.path.join(tmp, f"{s}.cvfarm.{r}.json"))) for r in range(1, int(repeats) + 1)]
    c = min(runs, key=lambda run: run["seconds"])
    e = {"scene": s, "renderer": "cvfarm", "seconds": c["seconds"], "samples_per_s": c["samples_per_s"],
         "rays_per_s": c["rays_per_s"], "rays_per_sample": c["rays"] / max(c["samples"], 1), "mean": c["mean"]}
    doc["entries"].append(e)
    for v in ["scalar_rgb", "llvm_ad_rgb"]:
        m = json.load(open(os.path.join(tmp, f"{s}.{v}.json")))
        doc["entries"].append({"scene": s, "renderer": f"mitsuba {mitsuba.__version__} {v}", "seconds": m["seconds"],
                               "samples_per_s": m["samples_per_s"], "rays_per_s": None,
                               "cold_seconds": m["cold_seconds"], "mean": m["mean"]})
json.dump(doc, open(out_json, "w"), indent=1)
lines = [
    "# cvfarm vs Mitsuba 3: render speed at equal spp",
    "",
    "Timing figures: valid only on an otherwise idle machine (check the load average first); rerun on",
    "an idle machine with `sh docs/perf/compare_mitsuba.sh [SPP]` (from the repository root).",
    "",
    f"Date {datetime.datetime.utcnow():%Y-%m-%d %H:%M} UTC, CPU {cpu}, {threads} threads, {res}x{res}, {spp} spp,",
    "max_depth 5, rr_depth 6 (no Russian roulette), path tracer with NEE + BSDF MIS (power heuristic),",
    "box filter. Same scene in both renderers (native JSON / the XML written by `make_scenes.py --mitsuba-xml`).",
    "Mitsuba renders once cold (listed), then the timed renders follow in the same process (llvm JIT excluded).",
    f"Each timed render was repeated {repeats} times; the table lists the fastest of each renderer.",
    f"Load average (1/5/15 min) at the start of the renders: {load_start}; at the end: {load_end}.",
    "",
    "| scene | renderer | seconds | samples/s | rays/s | rays/sample | cold run (s) | image mean RGB |",
    "|---|---|---|---|---|---|---|---|",
]
for e in doc["entries"]:
    rays = f"{e['rays_per_s'] / 1e6:.2f} M" if e.get("rays_per_s") else "–"
    rps = f"{e['rays_per_sample']:.2f}" if e.get("rays_per_sample") else "–"
    warm = f"{e['cold_seconds']:.2f}" if e.get("cold_seconds") is not None else "–"
    mean = ", ".join(f"{v:.4f}" for v in e["mean"])
    lines.append(f"| {e['scene']} | {e['renderer']} | {e['seconds']:.2f} | {e['samples_per_s'] / 1e6:.3f} M | {rays} | {rps} | {warm} | {mean} |")
lines += ["", "| scene | cvfarm / scalar_rgb (samples/s) | llvm_ad_rgb / cvfarm | max relative mean difference vs scalar_rgb |",
          "|---|---|---|---|"]
for s in ["cornell-box", "many-lights"]:
    es = {e["renderer"].split()[-1]: e for e in doc["entries"] if e["scene"] == s}
    c, sc, ll = es["cvfarm"], es["scalar_rgb"], es["llvm_ad_rgb"]
    diff = max(abs(a - b) / abs(b) for a, b in zip(c["mean"], sc["mean"]) if b != 0)
    lines.append(f"| {s} | {c['samples_per_s'] / sc['samples_per_s']:.2f}× | "
                 f"{ll['samples_per_s'] / c['samples_per_s']:.2f}× | {100 * diff:.2f} % |")
open(out_md, "w").write("\n".join(lines) + "\n")
print("\n".join(lines))
PY
rm -rf "$TMP"
