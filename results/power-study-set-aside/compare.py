#!/usr/bin/env python3
"""Each finished cell of this directory against the same cell of the default study
(`power-study-scoped/merge.py`'s cells: power-study-scoped, else power-study-nesting,
else power-study-eval-crn): outcome and the named cause's gain, default -> set aside,
and the objects flagged and set aside. Outcomes are the study tables' (power.csv:
every finished report decided again under today's rules), not report.json's `cause`,
which is the rules of the build that wrote it. Where nothing was flagged the cell's
candidates must equal the default's (gain and adjusted p); a cell where they do not is
marked. Then, per strength, the cells that flagged and set aside objects; over all
cells, how many named gains moved and fell; and the refined Monte Carlo sds over the
first ones (sqrt(1/8) expected at 8x the particles). Run from the repository root:
python3 results/power-study-set-aside/compare.py
"""
import glob
import json
import os
import statistics
import sys
from collections import Counter

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "power-study-scoped"))
from merge import ROOT, default_cells, rows, show  # noqa: E402

HERE = "power-study-set-aside"


def candidates(report):
    """Each candidate's gain and adjusted p, by cause."""
    return {c["cause"]: (round(c["gain"], 10), c["p_adjusted"]) for c in report["candidates"]}


def main():
    defaults, _ = default_cells()
    mine = rows(HERE)
    changed = uncompared = unequal = 0
    flagged_cells, set_aside_cells, moves, sd_ratios = Counter(), Counter(), [], []
    for path in sorted(glob.glob(f"{ROOT}/{HERE}/*/*/seed*/report.json")):
        effect, x, seed = path.split("/")[2:5]
        key = (effect, x[1:], seed[4:])
        source, old = defaults.get(key, (None, None))
        new = mine.get(key)
        report = json.load(open(path))
        flagged = report["eval_imprecise"]
        marks = []
        if old is None or new is None:
            uncompared += 1
            marks.append("not compared")
        elif old["cause"] != new["cause"]:
            changed += 1
            marks.append("changed")
        if not flagged and source is not None:
            default = json.load(open(f"{ROOT}/{source}/{effect}/{x}/{seed}/report.json"))
            if candidates(default) != candidates(report):
                unequal += 1
                marks.append("nothing flagged, candidates differ")
        set_aside = sum(o["set_aside"] for o in flagged)
        flagged_cells[x] += bool(flagged)
        set_aside_cells[x] += bool(set_aside)
        sd_ratios += [o["refined_mc_sd"] / o["mc_sd"] for o in flagged if o.get("refined_mc_sd") is not None]
        if old is not None and new is not None and old["cause"] == new["cause"] \
                and new["cause"] not in ("none", "unexplained") and old["gain"] != new["gain"]:
            moves.append(float(new["gain"]) - float(old["gain"]))
        mark = f"  <- {'; '.join(marks)}" if marks else ""
        print(f"{effect} {x} {seed}: {show(old)} -> {show(new)} | flagged {len(flagged)}, set aside {set_aside}{mark}")
    print(f"outcomes changed: {changed}; not compared: {uncompared}; "
          f"unflagged cells whose candidates differ: {unequal}")
    for x in sorted(flagged_cells, key=lambda x: float(x[1:])):
        print(f"{x}: cells that flagged objects {flagged_cells[x]}, that set some aside {set_aside_cells[x]}")
    print(f"named gains moved: {len(moves)}, fell: {sum(m < 0 for m in moves)}")
    if sd_ratios:
        print(f"objects refined: {len(sd_ratios)}; refined sd / first: median "
              f"{statistics.median(sd_ratios):.2f}, larger on {sum(r > 1 for r in sd_ratios)}")


if __name__ == "__main__":
    main()
