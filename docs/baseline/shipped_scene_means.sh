#!/bin/sh
# Mitsuba 3 image means of the shipped scenes (scenes/*/scene.json, rendered by Mitsuba through the
# identical XML that `scenes/make_scenes.py --mitsuba-xml` writes), used by crates/cli/tests/cli_scenes.rs
# to check that cvfarm renders every shipped scene like its peer does.
# Small resolutions with each scene's aspect ratio, max_depth 5 (2 for checkers, as the scene says),
# rr_depth = max_depth + 1 (no Russian roulette), 1024 spp in 4 passes of 256 (seed 11) -> mean and its
# standard error per channel.
# Usage (repo root): sh docs/baseline/shipped_scene_means.sh   -> crates/cli/tests/data/mitsuba_scene_means.json
set -e
ROOT=$(pwd)
TMP=$(mktemp -d)
TOOLS=${TOOLS:-/work/shared/scenes-mitsuba/tools}
OUT=$ROOT/crates/cli/tests/data/mitsuba_scene_means.json
if [ -z "$DRJIT_LIBLLVM_PATH" ]; then
  DRJIT_LIBLLVM_PATH=$(ldconfig -p | sed -n 's/.*libLLVM\.so\.19[^ ]* .*=> //p' | head -n1)
  export DRJIT_LIBLLVM_PATH
fi
python3 scenes/make_scenes.py --out "$TMP/native" --mitsuba-xml "$TMP/xml" 2>/dev/null
for spec in cornell-box:64:64:5 veach-mis:96:64:5 many-lights:64:64:5 envmap:80:60:5 colour-lamp:64:64:5 checkers:80:60:2; do
  IFS=: read -r n w h d <<EOT
$spec
EOT
  python3 "$TOOLS/render_ref.py" "$TMP/xml/$n/scene.xml" --variant llvm_ad_rgb --res "$w" "$h" --max-depth "$d" \
    --spp 1024 --pass-spp 256 --seed 11 -o "$TMP/$n.exr" --json "$TMP/$n.json" >&2
done
python3 - "$TMP" "$OUT" <<'PY'
import json, os, sys
tmp, out = sys.argv[1:3]
import mitsuba
entries = []
for n in ["cornell-box", "veach-mis", "many-lights", "envmap", "colour-lamp", "checkers"]:
    r = json.load(open(os.path.join(tmp, f"{n}.json")))
    entries.append({"scene": n, "width": r["width"], "height": r["height"], "max_depth": r["max_depth"],
                    "rr_depth": r["rr_depth"], "spp": r["spp"], "mean": r["mean_rgb"],
                    "rel_se": r["ref_rel_se_of_mean_rgb"]})
doc = {"how": "sh docs/baseline/shipped_scene_means.sh (Mitsuba renders of the XML twins written by "
              "scenes/make_scenes.py --mitsuba-xml; path integrator, box filter, independent sampler, "
              "4 passes of 256 spp, seeds 11000..11003)",
       "mitsuba": mitsuba.__version__ + " llvm_ad_rgb",
       "entries": entries}
with open(out, "w") as fh:
    json.dump(doc, fh, indent=1)
    fh.write("\n")
print("wrote", out)
PY
rm -rf "$TMP"
