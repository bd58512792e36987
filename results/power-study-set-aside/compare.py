#!/usr/bin/env python3
# Each finished cell of this directory against the same cell of the default study
# (power-study-scoped, else power-study-nesting, else power-study-eval-crn):
# outcome and the named cause's gain, default -> set aside, and the objects flagged
# and set aside. Run from the repository root: python3 results/power-study-set-aside/compare.py
import json,os,glob
for new in sorted(glob.glob('results/power-study-set-aside/*/x*/seed*/report.json')):
    parts=new.split('/'); e,x,k=parts[2],parts[3],parts[4]
    old=None
    for d in ['power-study-scoped','power-study-nesting','power-study-eval-crn']:
        o=f'results/{d}/{e}/{x}/{k}/report.json'
        if os.path.exists(o): old=o; break
    n=json.load(open(new)); oc=json.load(open(old)) if old else None
    im=n['eval_imprecise']
    def best(r):
        c=[c for c in r['candidates'] if c['cause']==r['cause']]
        return f"{c[0]['gain']:+.4f}" if c else ''
    print(f"{e} {x} {k}: {oc['cause'] if oc else '?'} {best(oc) if oc else ''} -> {n['cause']} {best(n)} | flagged {len(im)}, set aside {sum(o['set_aside'] for o in im)}")
