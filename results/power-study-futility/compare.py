"""The fitted screen with its futility stop (fortieth session, `--screen-futility`,
1/3 by default) against the same cells without it: the lean screen's
(`power-study-fitted-screen-lean/`) where it ran them, else the fitted screen's
(`power-study-fitted-screen/`). The data, seeds and every fit that was not stopped
are the same, so each candidate present in both has the same gain to the bit; a
stop can only turn an extension away. What changes is the work: each stopped
extension ends at the stop (step 50 of 150 here), and the reference in the
dynamics scope is not fitted where its every extension was stopped.

Time is measured in units of the base fit's time, the same fit in both runs, so
that a machine's speed on the day cancels. Run from the repository root:

    python3 results/power-study-futility/compare.py
"""
import glob
import json
import os

NEW = "results/power-study-futility"
EARLIER = ["results/power-study-fitted-screen-lean", "results/power-study-fitted-screen"]


def earlier_report(cell):
    for d in EARLIER:
        path = os.path.join(d, cell, "report.json")
        if os.path.exists(path):
            return d.split("/")[-1], json.load(open(path))
    return None, None


def admitted_before(r, plausible_p):
    """The extensions no check flagged that the screen admitted."""
    return {c["cause"] for c in r["candidates"]
            if c.get("check_part_p") is not None and c["check_part_p"] < plausible_p}


def main():
    print("| cell | compared with | outcome before → with the stop | gains equal | stopped (step) "
          "| stopped but admitted before | dynamics reference | cell in base-fit units | ratio |")
    print("|---|---|---|---|---|---|---|---|---|")
    ratios, changed, stops, screened = [], 0, 0, 0
    for path in sorted(glob.glob(f"{NEW}/*/x*/seed*/report.json")):
        cell = path[len(NEW) + 1:-len("/report.json")]
        where, old = earlier_report(cell)
        if old is None:
            continue
        new = json.load(open(path))
        before = {c["cause"]: c for c in old["candidates"]}
        both = [c for c in new["candidates"] if c["cause"] in before]
        equal = all(c["gain"] == before[c["cause"]]["gain"] for c in both)
        stopped = [n for n in new.get("not_admitted", []) if n.get("stopped_at") is not None]
        lost = sorted(admitted_before(old, old["config"]["plausible_p"]) & {n["cause"] for n in stopped})
        stops += len(stopped)
        screened += len([c for c in new["candidates"] if not c["flagged_by"]]) + len(new.get("not_admitted", []))
        changed += old["cause"] != new["cause"]
        dyn = f"{'yes' if old.get('dynamics_reference') else 'no'} → {'yes' if new.get('dynamics_reference') else 'no'}"
        u_old = old["seconds"] / old["base_train_seconds"]
        u_new = new["seconds"] / new["base_train_seconds"]
        ratios.append(u_new / u_old)
        stopped_ids = ", ".join(f"{n['cause']} ({n['stopped_at']})" for n in stopped) or "-"
        print(f"| {cell} | {where} | {old['cause']} → {new['cause']} | {'yes' if equal else 'NO'} | "
              f"{stopped_ids} | {', '.join(lost) or '-'} | "
              f"{dyn} | {u_old:.2f} → {u_new:.2f} | {u_new / u_old:.2f} |")
    if ratios:
        print(f"\n{len(ratios)} cells, {changed} with another outcome; {stops} of the {screened} screened fits "
              f"stopped; a cell takes {min(ratios):.2f}–{max(ratios):.2f} of its time without the stop "
              f"(mean {sum(ratios) / len(ratios):.2f}).")


if __name__ == "__main__":
    main()
