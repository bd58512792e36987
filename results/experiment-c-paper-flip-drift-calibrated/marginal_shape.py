"""How well each detection-error family fits KITTI's val detections around their labels,
one axis at a time (along / across the line of sight, yaw): mean log-density per
detection of the offsets under (a) the best Laplace (the white-noise model's family, what
the supervised fit learns), (b) a Laplace convolved with a Gaussian at given scales (the
drift model's marginal: white Laplace b, drift sd s) and (c) the best such convolution.
Detections more than 1 m / 0.5 rad from their label are left out (as the calibration
does). Standard library only. Usage: python3 marginal_shape.py K/val [b_along s_along b_across s_across b_yaw s_yaw]
"""
import csv, math, sys

def read(path):
    with open(path) as f:
        return list(csv.DictReader(f))

def offsets(d):
    states = {(r['scene'], r['object'], r['t']): r for r in read(f'{d}/states.csv')}
    av = {(r['scene'], r['t']): r for r in read(f'{d}/av.csv')}
    out = []
    for b in read(f'{d}/boxes.csv'):
        s = states.get((b['scene'], b['object'], b['t']))
        if s is None:
            continue
        a = av[(b['scene'], b['t'])]
        dx, dy = float(s['x']) - float(a['x']), float(s['y']) - float(a['y'])
        n = math.hypot(dx, dy) or 1e-6
        lx, ly = dx / n, dy / n
        ddx, ddy = float(b['x']) - float(s['x']), float(b['y']) - float(s['y'])
        yaw = (float(b['yaw']) - float(s['yaw']) + math.pi) % (2 * math.pi) - math.pi
        o = (ddx * lx + ddy * ly, ddy * lx - ddx * ly, yaw)
        if abs(o[0]) <= 1 and abs(o[1]) <= 1 and abs(o[2]) <= 0.5:
            out.append(o)
    return out

def log_laplace(x, b):
    return -abs(x) / b - math.log(2 * b)

def log_erfc(z):
    # ln erfc(z), stable for large z (Numerical Recipes' erfc in log form).
    if z < 0:
        return math.log(2 - math.erfc(-z))
    t = 1 / (1 + 0.5 * z)
    poly = (-z * z - 1.26551223 + t * (1.00002368 + t * (0.37409196 + t * (0.09678418 + t * (-0.18628806
            + t * (0.27886807 + t * (-1.13520398 + t * (1.48851587 + t * (-0.82215223 + t * 0.17087277)))))))))
    return math.log(t) + poly

def log_laplace_gauss(x, b, s):
    # Laplace(b) convolved with N(0, s^2), in closed form.
    r = s * s / (2 * b * b) - math.log(4 * b)
    u = r - x / b + log_erfc((s / b - x / s) / math.sqrt(2))
    v = r + x / b + log_erfc((s / b + x / s) / math.sqrt(2))
    m = max(u, v)
    return m + math.log(math.exp(u - m) + math.exp(v - m))

def log_laplace_laplace(x, b1, b2):
    # Laplace(b1) convolved with Laplace(b2), b1 != b2.
    return math.log((b1 * math.exp(-abs(x) / b1) - b2 * math.exp(-abs(x) / b2)) / (2 * (b1 * b1 - b2 * b2)))

def mean(f, xs):
    return sum(f(x) for x in xs) / len(xs)

def best(f, grid):
    return max((f(*p), p) for p in grid)

if __name__ == '__main__':
    d = sys.argv[1]
    given = [float(v) for v in sys.argv[2:8]] if len(sys.argv) >= 8 else None
    o = offsets(d)
    print(f'{len(o)} labelled detections')
    for k, name in enumerate(['along', 'across', 'yaw']):
        xs = [v[k] for v in o]
        b_ml = sum(abs(x) for x in xs) / len(xs)  # the Laplace's ML scale
        line = f'{name}: best Laplace b {b_ml:.4f}: {mean(lambda x: log_laplace(x, b_ml), xs):.4f}'
        if given:
            b, s = given[2 * k], given[2 * k + 1]
            line += f'; Laplace {b} * N({s}): {mean(lambda x: log_laplace_gauss(x, b, s), xs):.4f}'
        scale = b_ml
        grid = [(bf * scale, sf * scale) for bf in [0.2 + 0.05 * i for i in range(20)] for sf in [0.05 * i + 0.01 for i in range(30)]]
        v, (b, s) = best(lambda b, s: mean(lambda x: log_laplace_gauss(x, b, s), xs), grid)
        line += f'; best Laplace * N: b {b:.4f}, s {s:.4f}: {v:.4f}'
        pairs = [(f1 * scale, f2 * scale) for f1 in [0.05 * i for i in range(1, 21)] for f2 in [0.05 * i for i in range(1, 21)] if f1 < f2]
        v, (b1, b2) = best(lambda b1, b2: mean(lambda x: log_laplace_laplace(x, b1, b2), xs), pairs)
        line += f'; best Laplace * Laplace: {b1:.4f}, {b2:.4f}: {v:.4f}'
        print(line)
