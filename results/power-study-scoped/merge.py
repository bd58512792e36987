"""The default study under refit scopes, whole: every cell of `power-study-scoped`
where it was rediagnosed, the others from the directories whose diagnoses they equal.

Refit scopes change a diagnosis only where a candidate of the dynamics
(`heavy_tailed_accel`) is fitted; every other cell computes as before (checked to
the last digit on latency x0.5 seed 4). So a cell missing here is taken from
`power-study-nesting` (the flip cells rerun with nesting fits from their nested fit)
or else `power-study-eval-crn`. Each row of those directories' `power.csv` is the
cell as the binary decided it. Run from the repository root:

    python3 results/power-study-scoped/merge.py > results/power-study-scoped/merged.md
"""
import csv
import os

ROOT = "results"
SOURCES = ["power-study-scoped", "power-study-nesting", "power-study-eval-crn"]
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


def default_cells():
    """The default study, cell by cell: (effect, strength, seed) -> (source, row),
    each cell from the first of SOURCES that holds it; and every source's table."""
    tables = [rows(s) for s in SOURCES]
    cells = {}
    for key in tables[-1]:
        for source, table in zip(SOURCES, tables):
            if key in table:
                cells[key] = (source, table[key])
                break
    return cells, tables


def main():
    cells, tables = default_cells()
    effects = list(dict.fromkeys(k[0] for k in tables[-1]))
    strengths = ["0.5", "1", "2"]
    print("| effect | " + " | ".join(f"x {s}" for s in strengths) + " |")
    print("|---|" + "---|" * len(strengths))
    for e in effects:
        out = []
        for s in strengths:
            group = [cells[k] for k in sorted(cells) if k[0] == e and k[1] == s]
            if not group:
                out.append("")
                continue
            named = sum(r["named"] == "true" for _, r in group)
            false = sum(false_cause(e, r) for _, r in group)
            rerun = sum(src == SOURCES[0] for src, _ in group)
            note = f"{named} of {len(group)}"
            if false:
                note += f", {false} false"
            note += f" ({rerun} rerun)"
            out.append(note)
        print(f"| {e} | " + " | ".join(out) + " |")
    print()
    print("Cells whose outcome differs from the earlier directories':")
    for key in sorted(cells):
        source, r = cells[key]
        if source != SOURCES[0]:
            continue
        for old_source, table in zip(SOURCES[1:], tables[1:]):
            if key in table:
                if table[key]["cause"] != r["cause"]:
                    print(f"- {key[0]} x{key[1]} seed {key[2]}: {table[key]['cause']} ({old_source}) -> {r['cause']}")
                break


if __name__ == "__main__":
    main()
