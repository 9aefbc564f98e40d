#!/usr/bin/env python3
"""A phased estimator's overhead over `path` in executed instructions (deterministic).

This VM's speed drifts by 5-15 % between runs, so timed overheads of a few points carry
+-10 points. Instruction counts (`valgrind --tool=cachegrind`, no cache simulation) are the
same on every run: they show where the CV's work sits and whether a change removed any.
They are not time: a ray cast misses caches, CV bookkeeping mostly does not, so the
instruction overhead is larger than the time overhead (colour-lamp d5: about 2x).

Four single-thread renders: `path` and the estimator, each at its surrogate + training spp
(S0, read from the estimator's stats) and at S0 + N. Their differences split the overhead:

  fixed    = est(S0) - path(S0)          surrogate denoise, training records, solve
  per spp  = (est(S0+N) - est(S0) - path(S0+N) + path(S0)) / N    the render phase's CV work

and give the overhead at any spp S >= S0: (fixed + (S - S0) per spp) / (S path(1 spp)).
What the render phase costs once (its films, the EXR's CV layers) lands in `per spp`, divided
by N: with a switched-off job that is the whole of its +0.3 %.

    cargo build --release -p cli
    python3 docs/bench/instructions.py scenes/colour-lamp/scene.json --max-depth 5 \
        --res 96x96 --render-spp 32 [--estimator cms] [--sampler independent] [--top 12]

Needs valgrind (cg_annotate). Two renders run at a time.
"""

import argparse
import concurrent.futures
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile


def run(binary, scene, est, spp, args, tmp):
    """Instruction count of one render, and its per-function counts and stats."""
    tag = f"{est}_{spp}"
    out = os.path.join(tmp, f"cg_{tag}.out")
    stats = os.path.join(tmp, f"stats_{tag}.json")
    cmd = [
        "valgrind", "--tool=cachegrind", "--cache-sim=no", f"--cachegrind-out-file={out}",
        binary, "render", scene, "--spp", str(spp), "--threads", "1", "--estimator", est,
        "--seed", str(args.seed), "--res", args.res, "--sampler", args.sampler,
        "-o", os.path.join(tmp, f"img_{tag}.exr"), "--stats", stats,
    ]
    if args.max_depth is not None:
        cmd += ["--max-depth", str(args.max_depth)]
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode != 0:
        sys.exit(f"render failed ({' '.join(cmd)}):\n{p.stderr[-2000:]}")
    m = re.search(r"I\s+refs:\s+([0-9,]+)", p.stderr)
    if not m:
        sys.exit(f"no instruction count in valgrind's output:\n{p.stderr[-2000:]}")
    total = int(m.group(1).replace(",", ""))
    ann = subprocess.run(
        ["cg_annotate", "--threshold=0.001", "--auto=no", "--show-percs=no", out],
        capture_output=True, text=True, check=True,
    ).stdout
    funcs = {}
    body = ann.split("file:function", 1)[-1]
    for line in body.splitlines():
        m = re.match(r"^\s*([0-9,]+)\s+(\S.*)$", line)
        if not m:
            continue
        name = m.group(2)
        name = name.split(":", 1)[1] if ":" in name else name
        funcs[name] = funcs.get(name, 0) + int(m.group(1).replace(",", ""))
    with open(stats) as f:
        return total, funcs, json.load(f)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--estimator", default="cms")
    ap.add_argument("--max-depth", type=int)
    ap.add_argument("--res", default="96x96")
    ap.add_argument("--render-spp", type=int, default=32, help="N: render-phase spp measured")
    ap.add_argument("--sampler", default="independent")
    ap.add_argument("--seed", type=int, default=20)
    ap.add_argument("--top", type=int, default=12)
    ap.add_argument("--bin", default="target/release/cvfarm")
    args = ap.parse_args()
    if args.render_spp < 1:
        sys.exit("--render-spp must be at least 1")
    for tool in ("valgrind", "cg_annotate"):
        if shutil.which(tool) is None:
            sys.exit(f"{tool} not found (apt install valgrind)")
    if not os.path.exists(args.bin):
        sys.exit(f"{args.bin} not found (cargo build --release -p cli)")

    with tempfile.TemporaryDirectory() as tmp:
        # S0 from the estimator's own phases (a 1-spp probe render is cheap).
        probe = os.path.join(tmp, "probe.json")
        cmd = [args.bin, "render", args.scene, "--spp", "64", "--threads", "1",
               "--estimator", args.estimator, "--res", "8x8", "-o",
               os.path.join(tmp, "probe.exr"), "--stats", probe]
        p = subprocess.run(cmd, capture_output=True, text=True)
        if p.returncode != 0:
            sys.exit(f"render failed ({' '.join(cmd)}):\n{p.stderr[-2000:]}")
        with open(probe) as f:
            r = json.load(f).get("estimator_report") or {}
        s0 = int(r.get("surrogate_spp", 0)) + int(r.get("training_spp", 0))
        s1 = s0 + args.render_spp
        jobs = [("path", s0), (args.estimator, s0), ("path", s1), (args.estimator, s1)]
        with concurrent.futures.ThreadPoolExecutor(max_workers=2) as ex:
            res = dict(zip(jobs, ex.map(
                lambda j: run(args.bin, args.scene, j[0], j[1], args, tmp), jobs)))

    (p0, fp0, _), (e0, fe0, st0) = res[("path", s0)], res[(args.estimator, s0)]
    (p1, fp1, _), (e1, fe1, st1) = res[("path", s1)], res[(args.estimator, s1)]
    n = args.render_spp
    per_path = (p1 - p0) / n
    fixed = e0 - p0
    per_cv = ((e1 - e0) - (p1 - p0)) / n
    rep = st1.get("estimator_report") or {}
    print(f"{args.scene} {args.estimator} {args.res} d{args.max_depth} {args.sampler}, "
          f"seed {args.seed}: S0 = {s0} spp (surrogate + training), N = {n}")
    print(f"  cells solved {rep.get('cells_solved')} of {rep.get('cells')}; "
          f"fallbacks {rep.get('cells_fallback')}")
    print(f"  path: {per_path / 1e6:.1f} M instructions per spp")
    print(f"  fixed (surrogate, training, solve): {fixed / 1e6:.0f} M "
          f"= {fixed / per_path:.1f} spp of path")
    print(f"  render phase: +{per_cv / 1e6:.2f} M per spp = +{100 * per_cv / per_path:.1f} %")
    for s in (64, 128, 256, 1024):
        if s >= s0:
            o = (fixed + (s - s0) * per_cv) / (s * per_path)
            print(f"  overhead at {s:4d} spp: +{100 * o:.1f} % (instructions)")
    keys = set(fp0) | set(fp1) | set(fe0) | set(fe1)
    render = {k: (fe1.get(k, 0) - fe0.get(k, 0)) - (fp1.get(k, 0) - fp0.get(k, 0)) for k in keys}
    train = {k: fe0.get(k, 0) - fp0.get(k, 0) for k in keys}
    skip = {"PROGRAM TOTALS", "events annotated"}
    for title, d, scale in (("render phase, per spp", render, n), ("fixed", train, 1)):
        print(f"  {title} (M instructions, by function):")
        for k in sorted((k for k in d if k not in skip), key=lambda k: -d[k])[: args.top]:
            print(f"    {d[k] / scale / 1e6:9.2f}  {k[:100]}")


if __name__ == "__main__":
    main()
