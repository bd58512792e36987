"""The fitted screen with its futility stop (fortieth session, `--screen-futility`,
1/3 by default) against the same cells without it: the lean screen's
(`power-study-fitted-screen-lean/`) where it ran them, else the fitted screen's
(`power-study-fitted-screen/`). The data, seeds and every fit that was not stopped
are the same, so each candidate present in both has the same gain to the bit; a
stop can only turn an extension away. What changes is the work: each stopped
extension ends at the stop (step 50 of 150 here), and the reference in the
dynamics scope is not fitted where its every extension was stopped.

The work is counted in training steps (the base's, every extension's to its end
or its stop, the references' and reseeded refits'), which no machine's speed or
load changes; the cells' wall time is shown in units of the base fit's time
(the same fit in both runs), which cancels the day's speed but not another
process's load during the cell. Run from the repository root:

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


def fit_steps(r):
    """Training steps of every fit of a diagnosis (a stopped one to its stop)."""
    refit = r["config"]["candidate_steps"]
    steps = r["config"]["base_steps"] + refit * len(r["candidates"])
    steps += sum(n.get("stopped_at") or refit for n in r.get("not_admitted", []))
    for key in ("reference", "dynamics_reference"):
        if r.get(key):
            steps += refit * (1 + (r[key].get("reseeded") is not None))
    return steps


def same_object_gains(new, c_new, old, c_old):
    """Whether a candidate's gain is the same on every evaluation object both
    diagnoses kept. The earlier fitted screen also evaluated the extensions it
    did not admit, and an object one of them did not measure was set aside; the
    lean screen (and so this one) judges that over the models it compares."""
    by_key = lambda r, c: dict(zip(map(str, r["eval_object_keys"]), c["object_gains"]))
    a, b = by_key(new, c_new), by_key(old, c_old)
    return all(a[k] == b[k] for k in (a.keys() & b.keys()) - refined_in_one(new, old))


def refined_in_one(new, old):
    """The objects one diagnosis refiltered with more particles and the other did
    not: an object is refined where some model it compares measures it
    imprecisely, and the models compared differ (a stopped extension is not
    evaluated, nor the dynamics reference where it is not fitted)."""
    refined = lambda r: {str([o["scene"], o["id"]]) for o in r.get("eval_imprecise", [])}
    return refined(new) ^ refined(old)


def admitted_before(r, plausible_p):
    """The extensions no check flagged that the screen admitted."""
    return {c["cause"] for c in r["candidates"]
            if c.get("check_part_p") is not None and c["check_part_p"] < plausible_p}


def main():
    print("| cell | compared with | outcome before → with the stop | gains equal by object | stopped (step) "
          "| stopped but admitted before | dynamics reference | fit steps | ratio | cell in base-fit units | ratio |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    ratios, step_ratios, changed, stops, screened = [], [], 0, 0, 0
    by_effect = {}
    for path in sorted(glob.glob(f"{NEW}/*/x*/seed*/report.json")):
        cell = path[len(NEW) + 1:-len("/report.json")]
        where, old = earlier_report(cell)
        if old is None:
            continue
        new = json.load(open(path))
        before = {c["cause"]: c for c in old["candidates"]}
        both = [c for c in new["candidates"] if c["cause"] in before]
        equal = all(same_object_gains(new, c, old, before[c["cause"]]) for c in both)
        kept_apart = len(set(map(str, new["eval_object_keys"])) ^ set(map(str, old["eval_object_keys"])))
        refined_apart = len(refined_in_one(new, old))
        stopped = [n for n in new.get("not_admitted", []) if n.get("stopped_at") is not None]
        lost = sorted(admitted_before(old, old["config"]["plausible_p"]) & {n["cause"] for n in stopped})
        stops += len(stopped)
        screened += len([c for c in new["candidates"] if not c["flagged_by"]]) + len(new.get("not_admitted", []))
        changed += old["cause"] != new["cause"]
        dyn = f"{'yes' if old.get('dynamics_reference') else 'no'} → {'yes' if new.get('dynamics_reference') else 'no'}"
        u_old = old["seconds"] / old["base_train_seconds"]
        u_new = new["seconds"] / new["base_train_seconds"]
        ratios.append(u_new / u_old)
        s_old, s_new = fit_steps(old), fit_steps(new)
        step_ratios.append(s_new / s_old)
        group = by_effect.setdefault(cell.split("/")[0] + " x" + cell.split("/")[1][1:], [])
        n_screened = len([c for c in new["candidates"] if not c["flagged_by"]]) + len(new.get("not_admitted", []))
        group.append((old["cause"], new["cause"], equal, len(stopped), n_screened, lost, s_new / s_old, u_new / u_old))
        stopped_ids = ", ".join(f"{n['cause']} ({n['stopped_at']})" for n in stopped) or "-"
        equal_text = ("yes" if equal else "NO") + (f" ({kept_apart} object set aside in one only)" if kept_apart else "")
        equal_text += f" ({refined_apart} object refined in one only)" if refined_apart else ""
        print(f"| {cell} | {where} | {old['cause']} → {new['cause']} | {equal_text} | "
              f"{stopped_ids} | {', '.join(lost) or '-'} | "
              f"{dyn} | {s_old} → {s_new} | {s_new / s_old:.2f} | {u_old:.2f} → {u_new:.2f} | {u_new / u_old:.2f} |")
    print("\n| cells | outcomes before → with the stop | gains equal by object | screened fits stopped | stopped but admitted "
          "before | fit steps, ratio | wall time in base-fit units, ratio |")
    print("|---|---|---|---|---|---|---|")
    for effect, rows in by_effect.items():
        outcomes = lambda i: ", ".join(f"{n} {c}" for c, n in sorted(
            {c: sum(r[i] == c for r in rows) for c in {r[i] for r in rows}}.items()))
        lost = sum(len(r[5]) for r in rows)
        print(f"| {effect}, {len(rows)} seeds | {outcomes(0)} → {outcomes(1)} | "
              f"{'all' if all(r[2] for r in rows) else 'NOT all'} | {sum(r[3] for r in rows)} of {sum(r[4] for r in rows)} | "
              f"{lost} | {min(r[6] for r in rows):.2f}–{max(r[6] for r in rows):.2f} | "
              f"{min(r[7] for r in rows):.2f}–{max(r[7] for r in rows):.2f} |")
    if ratios:
        print(f"\n{len(ratios)} cells, {changed} with another outcome; {stops} of the {screened} screened fits "
              f"stopped; a cell's fits take {min(step_ratios):.2f}–{max(step_ratios):.2f} of their steps without "
              f"the stop (mean {sum(step_ratios) / len(step_ratios):.2f}), its wall time in base-fit units "
              f"{min(ratios):.2f}–{max(ratios):.2f} (mean {sum(ratios) / len(ratios):.2f}).")


if __name__ == "__main__":
    main()
