#!/usr/bin/env python3
"""Each cell of this directory's `power.csv` against the same cell of the default
study (`power-study-set-aside/power.csv`): the outcome with the fitted screen and
without it, each as the study tables decide it today (every finished report decided
again under the current rules). Then, per effect and strength, how many seeds gave
the expected outcome on each side, and the false causes (a catalogue cause other than
the expected one) over every compared cell. Rebuild both tables first (`sefi
power-study --table-only ...`, see results/README.md), then run from the repository
root: python3 results/power-study-fitted-screen/compare.py
"""
import os
import sys
from collections import defaultdict

import csv  # noqa: E402

ROOT = "results"
EXPECTED = {"student_t_accel": "heavy_tailed_accel", "ego_pose_noise": "unexplained",
            "none-points": "none", "none-boxes": "none"}


def rows(source):
    """One study's `power.csv` by cell, (effect, strength, seed) -> row."""
    path = os.path.join(ROOT, source, "power.csv")
    return {(r["effect"], r["strength"], r["seed"]): r for r in csv.DictReader(open(path))}


def show(row):
    """A cell's outcome, with the named cause's gain ("?" for a missing cell)."""
    if row is None:
        return "?"
    named = row["cause"] not in ("none", "unexplained")
    return row["cause"] + (f" {float(row['gain']):+.4f}" if named else "")


def false_cause(effect, row):
    """Whether the cell names a catalogue cause other than the effect's expected one."""
    return row["cause"] not in (EXPECTED.get(effect, effect), "none", "unexplained")


def main():
    screened = rows("power-study-fitted-screen")
    default = rows("power-study-set-aside")
    counts = defaultdict(lambda: [0, 0, 0])
    false = [0, 0]
    print("| cell | without the screen | fitted screen |")
    print("|---|---|---|")
    for key in sorted(screened, key=lambda k: (k[0], k[1], int(k[2]))):
        effect, strength, seed = key
        mine, theirs = screened[key], default.get(key)
        print(f"| {effect} x{strength} seed {seed} | {show(theirs)} | {show(mine)} |")
        if theirs is None:
            continue
        count = counts[(effect, strength)]
        count[0] += 1
        count[1] += theirs["named"] == "true"
        count[2] += mine["named"] == "true"
        false[0] += false_cause(effect, theirs)
        false[1] += false_cause(effect, mine)
    print()
    print("| effect | strength | seeds compared | expected, without | expected, fitted screen |")
    print("|---|---|---|---|---|")
    for (effect, strength), (n, without, with_screen) in sorted(counts.items()):
        print(f"| {effect} | {strength} | {n} | {without} | {with_screen} |")
    total = sum(c[0] for c in counts.values())
    print(f"\nfalse causes over {total} compared cells: {false[0]} without the screen, {false[1]} with it")


if __name__ == "__main__":
    main()
