#!/bin/sh
# Mitsuba 3 baseline at 256 spp: how noisy is the *peer* renderer at the spp our tests use?
# For each shared scene and max_depth 2/5: render with Mitsuba (seed 7; the references use seeds 1 and 2),
# compare with the 4096-spp reference, write crates/render/tests/data/mitsuba_256spp.json.
# Usage (from the repo root): sh docs/baseline/mitsuba_256spp.sh [SHARED_DIR]
set -e
SHARED=${1:-/work/shared/scenes-mitsuba}
OUT=$(pwd)/crates/render/tests/data/mitsuba_256spp.json
TMP=$(mktemp -d)
VARIANT=${VARIANT:-llvm_ad_rgb}
if [ -z "$DRJIT_LIBLLVM_PATH" ]; then
  DRJIT_LIBLLVM_PATH=$(ldconfig -p | sed -n 's/.*libLLVM\.so\.19[^ ]* .*=> //p' | head -n1)
  export DRJIT_LIBLLVM_PATH
fi
for s in cbox manylights-4 bsdf-spheres/roughplastic-ggx bsdf-spheres/roughconductor-ggx; do
  n=$(basename $s)
  for d in 2 5; do
    python3 "$SHARED/tools/render_ref.py" "$SHARED/$s/scene.xml" --variant "$VARIANT" --max-depth $d \
      --spp 256 --pass-spp 256 --seed 7 -o "$TMP/${n}_d$d.exr" --json "$TMP/${n}_d$d.render.json"
    python3 "$SHARED/tools/compare.py" "$TMP/${n}_d$d.exr" "$SHARED/refs/${n}_d$d.exr" --json "$TMP/${n}_d$d.cmp.json"
  done
done
python3 - "$TMP" "$OUT" "$VARIANT" <<'PY'
import json, sys, os
tmp, out, variant = sys.argv[1:4]
import mitsuba
entries = []
for n in ["cbox", "manylights-4", "roughplastic-ggx", "roughconductor-ggx"]:
    for d in [2, 5]:
        r = json.load(open(os.path.join(tmp, f"{n}_d{d}.render.json")))
        c = json.load(open(os.path.join(tmp, f"{n}_d{d}.cmp.json")))
        entries.append({"scene": n, "max_depth": d, "spp": 256, "seed": 7,
                        "rel_mse": c["relMSE"], "mse": c["MSE"],
                        "mean": r["mean_rgb"], "ref_mean": c["mean_ref_rgb"],
                        "mean_ratio": c["mean_ratio_rgb"], "nonfinite_frac": c["nonfinite_frac"],
                        "render_wall_s": r["render_wall_s"]})
doc = {
    "how": "sh docs/baseline/mitsuba_256spp.sh  # per scene S and D in {2,5}: python3 tools/render_ref.py S/scene.xml "
           "--variant " + variant + " --max-depth D --spp 256 --pass-spp 256 --seed 7 -o X.exr; "
           "python3 tools/compare.py X.exr refs/<name>_dD.exr  (tools/ and refs/ of /work/shared/scenes-mitsuba; "
           "128x128, box filter, path integrator, rr_depth = max_depth + 1, independent sampler)",
    "mitsuba": mitsuba.__version__ + " " + variant,
    "reference": "refs/<scene>_d<D>.exr, 4096 spp, seeds 1 (d2) and 2 (d5)",
    "metric": "rel_mse = mean over pixels and channels of (x - ref)^2 / (ref^2 + 0.01); mean = image mean RGB of the 256-spp render",
    "entries": entries,
}
os.makedirs(os.path.dirname(out), exist_ok=True)
with open(out, "w") as fh:
    json.dump(doc, fh, indent=1)
    fh.write("\n")
print("wrote", out)
PY
rm -rf "$TMP"
