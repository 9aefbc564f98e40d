#!/usr/bin/env python3
"""Prints the summary table of docs/bench/README.md from the bench.md files next to it."""
import pathlib

root = pathlib.Path(__file__).parent
print("| scene / depth | estimator | equal-time speedup | equal-sample speedup (spp) | time overhead |")
print("|---|---|---|---|---|")
for md in sorted(root.glob("**/bench.md")):
    rel = md.parent.relative_to(root).as_posix()
    for line in md.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 7 and cells[0] not in ("estimator", "path") and not cells[0].startswith("---"):
            print(f"| [{rel}]({rel}/bench.md) | {cells[0]} | {cells[1]} | {cells[2]} | {cells[3]} |")
        if line.startswith("## Series"):
            break
