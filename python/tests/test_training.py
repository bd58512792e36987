"""A short training run of the stochastic-volatility example: the held-out
log-likelihood improves and the parameters move towards the truth."""

import importlib.util
import pathlib

import numpy as np

EXAMPLE = pathlib.Path(__file__).resolve().parents[2] / "examples" / "python" / "stochastic_volatility.py"


def load_example():
    spec = importlib.util.spec_from_file_location("stochastic_volatility", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_short_training_run_improves_held_out_loglik():
    sv = load_example()
    history = sv.learn(iterations=40, objects=8, steps=60, particles=128, lr=0.05, log=lambda *_: None)
    start, end = history[0], history[-1]
    # From START (phi 0.3, sigma 1.2, beta 2.0) the held-out log-likelihood per
    # observation rises by well over its particle noise (about 0.005 at N = 128).
    assert end[2] > start[2] + 0.05, (start[2], end[2])
    # Every parameter is closer to the truth than where it started.
    assert np.all(np.abs(end[1] - sv.TRUTH) < np.abs(start[1] - sv.TRUTH)), end[1]
