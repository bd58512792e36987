"""The lean fitted screen (thirty-ninth session) against the fitted screen of the
thirty-seventh and thirty-eighth sessions, cell by cell: the same data, seeds and
fits, so every candidate's gain must be the same to the bit, and the outcome the
same; what changes is the work. The lean screen neither checks again nor evaluates
an extension it did not admit, and fits a scope's reseeded refit only where the
scope has a candidate.

Time is measured in units of the fits both runs made alike (the base, every
extension, the references), so that a machine's speed on the day cancels. Run
from the repository root:

    python3 results/power-study-fitted-screen-lean/compare.py
"""
import glob
import json
import os

OLD = "results/power-study-fitted-screen"
NEW = "results/power-study-fitted-screen-lean"


def shared_fits(r):
    """Seconds of the fits both runs made (base, extensions, references), the
    reseeded refits' seconds, and the rest (checks and evaluations)."""
    shared = r["base_train_seconds"] + sum(c["train_seconds"] for c in r["candidates"])
    shared += sum(n["train_seconds"] for n in r.get("not_admitted", []))
    reseeded = 0.0
    for key in ("reference", "dynamics_reference"):
        if r.get(key):
            shared += r[key]["train_seconds"]
            if r[key].get("reseeded"):
                reseeded += r[key]["reseeded"]["train_seconds"]
    return shared, reseeded, r["seconds"] - shared - reseeded


def main():
    print("| cell | outcome before → lean | gains equal | largest change of a p adj. | not admitted | reseeded refits (s) | checks and evaluations (s) | cell in shared-fit units | ratio |")
    print("|---|---|---|---|---|---|---|---|---|")
    ratios = []
    for path in sorted(glob.glob(f"{NEW}/*/x*/seed*/report.json")):
        cell = path[len(NEW) + 1:-len("/report.json")]
        old_path = os.path.join(OLD, cell, "report.json")
        if not os.path.exists(old_path):
            continue
        old, new = json.load(open(old_path)), json.load(open(path))
        (s_old, r_old, rest_old), (s_new, r_new, rest_new) = shared_fits(old), shared_fits(new)
        before = {c["cause"]: c for c in old["candidates"]}
        equal = all(c["gain"] == before[c["cause"]]["gain"] for c in new["candidates"])
        dp = max([abs(c["p_adjusted"] - before[c["cause"]]["p_adjusted"]) for c in new["candidates"]] or [0.0])
        u_old, u_new = old["seconds"] / s_old, new["seconds"] / s_new
        ratios.append(u_new / u_old)
        print(f"| {cell} | {old['cause']} → {new['cause']} | {'yes' if equal else 'NO'} | {dp:.4f} | "
              f"{len(new.get('not_admitted', []))} | {r_old:.0f} → {r_new:.0f} | {rest_old:.0f} → {rest_new:.0f} | "
              f"{u_old:.2f} → {u_new:.2f} | {u_new / u_old:.2f} |")
    if ratios:
        print(f"\n{len(ratios)} cells; the lean cell takes {min(ratios):.2f}–{max(ratios):.2f} of the earlier one's time "
              f"(mean {sum(ratios) / len(ratios):.2f}).")


if __name__ == "__main__":
    main()
