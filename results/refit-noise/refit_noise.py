"""How far apart two refits of the same model land: in every committed diagnosis
of the power studies under today's protocol and of the Student-t at the default
scale, the reseeded refit's held-out gain over its reference (the base refitted
alone, in the same scope, with another training seed: rule (b)'s yardstick), by
data kind and refit scope. Rule (b) asks a cause to beat both refits by the
0.003 minimum, so where the two differ by that much the refits' own noise, not
the evaluation's sample, sets the smallest effect the protocol names. Reports
that kept no per-object gains of the reseeded refit (before 2026-11-27) are
left out. Standard library only; run from the repository root:

    python3 results/refit-noise/refit_noise.py
"""
import glob
import json
import statistics as S

MIN_GAIN = 0.003
STUDIES = ["power-study-set-aside", "power-study-fitted-screen", "power-study-futility", "diagnose-student-t-default"]
SCOPES = {"reference": "every parameter", "dynamics_reference": "the policy alone"}

rows = {}
for study in STUDIES:
    for path in glob.glob(f"results/{study}/**/report.json", recursive=True):
        r = json.load(open(path))
        for key, scope in SCOPES.items():
            ref = r.get(key)
            reseeded = ref and ref.get("reseeded")
            if reseeded and reseeded.get("object_gains"):
                rows.setdefault((r["kind"], scope), []).append((reseeded["gain"], reseeded["gain_se"]))

print("| data | refit scope | diagnoses | median |gain| | share with |gain| >= 0.003 | share above 2 SE | largest |gain| |")
print("|---|---|---|---|---|---|---|")
for (kind, scope), v in sorted(rows.items()):
    a = [abs(g) for g, _ in v]
    above = sum(abs(g) > 2 * se for g, se in v if se > 0) / len(v)
    print(
        f"| {kind} | {scope} | {len(v)} | {S.median(a):.4f} | {sum(x >= MIN_GAIN for x in a) / len(a):.0%} "
        f"| {above:.0%} | {max(a):.4f} |"
    )
