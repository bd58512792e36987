"""Two stronger bars for the fitted screen, read off the committed cells and not
built (forty-first session). Neither needs a run: every cell of this study keeps
each fit's check-part evaluations (`eval.csv`, every `keep_best_every` steps).

1. The reference at the same step. The futility stop continues a screened
   extension only where its best check-part evaluation by the stop is above the
   base's kept value, which is where its scope's reference starts. A bar at the
   reference's own best by the same step is stronger (the reference starts at
   the base and can only raise its best). For every screened extension that went
   on, this prints whether that bar would also have stopped it, and what became
   of it in the end (admitted, named).

2. The screen's admission level. Over both fitted-screen studies (this one and
   `power-study-fitted-screen/`), the check-part p of every screened extension
   that was admitted, and whether it was the hidden effect's own extension.

Run from the repository root:

    python3 results/power-study-futility/bars.py
"""
import csv
import glob
import json
import math
import os

from compare import fit_steps

STUDY = "results/power-study-futility"
BOTH = [STUDY, "results/power-study-fitted-screen"]
REFERENCE_DIR = {"all": "reference", "dynamics": "reference-dynamics"}
# The catalogue cause each hidden effect should be named as.
EXPECTED = {
    "heavy_tailed_accel": "heavy_tailed_accel",
    "student_t_accel": "heavy_tailed_accel",
    "latency": "latency",
    "clutter": "clutter",
    "size_bias": "size_bias",
    "heading_flip": "heading_flip",
    "persistent_flip": "persistent_flip",
}


def evaluations(path):
    with open(path) as f:
        return [(int(row[0]), float(row[1])) for row in list(csv.reader(f))[1:]]


def best_by(evals, step):
    return max(value for s, value in evals if s <= step)


def stop_step(config):
    every = config["keep_best_every"]
    return math.ceil(config["screen_futility"] * config["candidate_steps"] / every) * every


def cells(directory):
    for path in sorted(glob.glob(f"{directory}/*/x*/seed*/report.json")):
        yield os.path.dirname(path), json.load(open(path))


def reference_bar():
    went_on = stopped = saved = 0
    total = 0
    print("## 1. A bar at the scope reference's best by the stop\n")
    print("| cell | extension | its best by the stop | reference's | difference | in the end |")
    print("|---|---|---|---|---|---|")
    for cell, r in cells(STUDY):
        config = r["config"]
        k, steps = stop_step(config), config["candidate_steps"]
        total += fit_steps(r)
        fits = [(c, True) for c in r["candidates"]] + [(n, False) for n in r["not_admitted"]]
        for fit, admitted in fits:
            screened = not fit.get("flagged_by") and fit["cause"] != "heading_flip"
            if not screened or fit.get("stopped_at") is not None:
                continue
            went_on += 1
            own = best_by(evaluations(f"{cell}/candidates/{fit['cause']}/eval.csv"), k)
            scope = fit["refit_scope"]
            reference = best_by(evaluations(f"{cell}/{REFERENCE_DIR[scope]}/eval.csv"), k)
            if own <= reference:
                stopped += 1
                saved += steps - k
                end = "named" if fit["cause"] == r["cause"] else ("admitted" if admitted else "not admitted")
                name = cell[len(STUDY) + 1 :]
                print(f"| {name} | {fit['cause']} | {own:.4f} | {reference:.4f} | {own - reference:+.5f} | {end} |")
    print(
        f"\n{went_on} screened fits went on past the stop; the reference's bar would also stop {stopped}, "
        f"saving {saved} of the cells' {total} fit steps ({saved / total:.1%}).\n"
    )


def admission_levels():
    print("## 2. The check-part p of every screened extension the screen admitted\n")
    print("| study | cell | extension | check-part p | the hidden effect's | named |")
    print("|---|---|---|---|---|---|")
    rows = []
    for directory in BOTH:
        for cell, r in cells(directory):
            effect = cell.split("/")[2]
            for c in r["candidates"]:
                p = c.get("check_part_p")
                if c["flagged_by"] or p is None or p >= r["config"]["plausible_p"]:
                    continue
                own = c["cause"] == EXPECTED.get(effect)
                rows.append((p, directory.split("/")[-1], cell[len(directory) + 1 :], c["cause"], own, c["cause"] == r["cause"]))
    for p, study, cell, cause, own, named in sorted(rows):
        print(f"| {study} | {cell} | {cause} | {p:.4f} | {'yes' if own else 'no'} | {'yes' if named else 'no'} |")
    named = [p for p, *_, named in rows if named]
    chance = [p for p, _, _, _, own, _ in rows if not own]
    print(
        f"\n{len(rows)} admissions; the {len(named)} that ended named had p <= {max(named):.4f}; "
        f"{len(chance)} were not the hidden effect's extension, {sum(p < 0.01 for p in chance)} of them at p < 0.01."
    )


if __name__ == "__main__":
    reference_bar()
    admission_levels()
