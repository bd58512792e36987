"""Benchmark (not a test): what calling PF-SEFI from Python costs.

1. The Python call's overhead over the Rust call for the size-A PF-SEFI step
   (the vehicle model with point observations on one synthetic scene, T = 25,
   N = 1024, L = 8, f32, seed 1: the workload of `cargo bench --bench estimators`):
   the wall time of `SyntheticScene.score_timed` from Python against the time the
   same estimate took inside Rust in that call. Median of the repetitions.
2. The per-step cost of a model written in Python (NumPy callbacks) against the
   same linear-Gaussian model in Rust: PF-SEFI with N particles on one sequence,
   per filter step (both single-threaded over one object).

    python python/bench/overhead.py [--reps 5]
"""

import argparse
import statistics
import time

import numpy as np

import pfsefi
from pfsefi.models import LinearGaussianCallbacks


def size_a(reps):
    scene = pfsefi.SyntheticScene(transitions=25, seed=3)
    scene.score_timed()  # warm-up
    walls, rusts = [], []
    for _ in range(reps):
        t0 = time.perf_counter()
        result, rust = scene.score_timed()
        walls.append(time.perf_counter() - t0)
        rusts.append(rust)
    wall, rust = statistics.median(walls), statistics.median(rusts)
    over = [(w - r) / r for w, r in zip(walls, rusts)]
    print(f"size A PF-SEFI step ({scene.num_objects} objects, T = 25, N = 1024, L = 8, f32), {reps} repetitions:")
    print(f"  Python call (wall)  median {wall * 1e3:9.1f} ms")
    print(f"  Rust estimate       median {rust * 1e3:9.1f} ms")
    print(f"  overhead            median {100 * statistics.median(over):6.2f} %  (max {100 * max(over):.2f} %; aim <= 5 %)")
    print(f"  loglik {result['loglik']:.3f}, {len(result['score'])} parameter tensors, "
          f"{result['rows_evaluated']} distinct ancestors")


def callbacks(reps, steps=200):
    model = pfsefi.LinearGaussian(0.9, 0.5, 0.8)
    cb = LinearGaussianCallbacks(model.m0, model.p0)
    _, y = model.simulate(steps, seed=0)
    print(f"\nper filter step, PF-SEFI (L = 10, f64) on one linear-Gaussian sequence of {steps} steps:")
    print(f"  {'N':>6} {'Rust (us/step)':>15} {'callbacks (us/step)':>20} {'ratio':>7}")
    for n in [256, 1024, 4096]:
        rust, py = [], []
        for r in range(reps):
            t0 = time.perf_counter()
            model.score(y[0], particles=n, lag=10, seed=r)
            rust.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            pfsefi.particle_filter(cb, y[0], model.theta, particles=n, lag=10, seed=r)
            py.append(time.perf_counter() - t0)
        a, b = statistics.median(rust) / steps * 1e6, statistics.median(py) / steps * 1e6
        print(f"  {n:>6} {a:>15.1f} {b:>20.1f} {b / a:>7.1f}x")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reps", type=int, default=5)
    args = ap.parse_args()
    size_a(args.reps)
    callbacks(args.reps)
