#!/usr/bin/env python3
# Each finished cell of this directory against the same cell of the default study
# (power-study-scoped, else power-study-nesting, else power-study-eval-crn): outcome and
# the named cause's gain, default -> set aside, and the objects flagged and set aside.
# Outcomes are the study tables' (power.csv: every finished report decided again under
# today's rules), not report.json's `cause`, which is the rules of the build that wrote it.
# Run from the repository root: python3 results/power-study-set-aside/compare.py
import csv, glob, json, os

def outcomes(d):
    with open(f'results/{d}/power.csv') as f:
        return {(r['effect'], r['strength'], r['seed']): r for r in csv.DictReader(f)}

defaults = {d: outcomes(d) for d in ['power-study-scoped', 'power-study-nesting', 'power-study-eval-crn']}
mine = outcomes('power-study-set-aside')

changed = 0
for new in sorted(glob.glob('results/power-study-set-aside/*/*/seed*/report.json')):
    parts = new.split('/')
    e, x, k = parts[2], parts[3], parts[4]
    key = (e, x[1:], k[4:])
    old = None
    for d, table in defaults.items():
        if os.path.exists(f'results/{d}/{e}/{x}/{k}/report.json') and key in table:
            old = table[key]
            break
    n = mine.get(key)
    im = json.load(open(new))['eval_imprecise']
    def show(row):
        if row is None:
            return '?'
        named = row['cause'] not in ('none', 'unexplained')
        return row['cause'] + (f" {float(row['gain']):+.4f}" if named else '')
    flag = '' if old is None or n is None or old['cause'] == n['cause'] else '  <- changed'
    changed += bool(flag)
    print(f"{e} {x} {k}: {show(old)} -> {show(n)} | flagged {len(im)}, set aside {sum(o['set_aside'] for o in im)}{flag}")
print(f"outcomes changed: {changed}")
