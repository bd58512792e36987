"""Are KITTI's reversed headings independent from detection to detection, as the
catalogue's `heading_flip` assumes? Per split of a `sefi import-kitti` dataset: the share
of detections whose heading is more than pi/2 from their label's, how many objects have
any against what independent flips at that rate would give, the dispersion index of the
per-object counts (1 for independent flips), and the chance that a detection is reversed
when the same object's detection one step before was. Standard library only.
Usage: python3 flip_persistence.py K/train K/val
"""
import collections
import csv
import math
import sys


def read(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def reversals(d):
    """Per object, its (step, reversed against the label) pairs in step order."""
    states = {(r['scene'], r['object'], r['t']): r for r in read(f'{d}/states.csv')}
    per = collections.defaultdict(list)
    for b in read(f'{d}/boxes.csv'):
        s = states.get((b['scene'], b['object'], b['t']))
        if s is None:
            continue
        dy = (float(b['yaw']) - float(s['yaw']) + math.pi) % (2 * math.pi) - math.pi
        per[(b['scene'], b['object'])].append((int(b['t']), abs(dy) > math.pi / 2))
    return {k: sorted(v) for k, v in per.items()}


for d in sys.argv[1:]:
    per = reversals(d)
    n = [len(v) for v in per.values()]
    k = [sum(x[1] for x in v) for v in per.values()]
    p = sum(k) / sum(n)
    expected_any = sum(1 - (1 - p) ** m for m in n)
    dispersion = sum((a - m * p) ** 2 / (m * p * (1 - p)) for a, m in zip(k, n)) / len(n)
    majority = [(a, m) for a, m in zip(k, n) if a > m / 2]
    pairs = both = 0
    for v in per.values():
        for (t0, a), (t1, b) in zip(v, v[1:]):
            if t1 == t0 + 1 and a:
                pairs += 1
                both += b
    print(
        f"{d}: {sum(n)} detections, {sum(k)} reversed ({p:.1%}); {len(n)} objects, "
        f"{sum(1 for a in k if a)} with any reversed against {expected_any:.0f} if independent, "
        f"{len(majority)} with most reversed (carrying {sum(a for a, _ in majority)}); dispersion {dispersion:.1f} "
        f"(1 if independent); P(reversed | reversed the step before) {both / pairs:.2f} ({pairs} pairs)"
    )
