"""The vehicle model on a synthetic scene: the score of every estimator by parameter name."""

import numpy as np
import pytest

import pfsefi


@pytest.fixture(scope="module")
def scene():
    return pfsefi.SyntheticScene(transitions=5, seed=3)


def test_score_is_a_dict_by_parameter_name(scene):
    r = scene.score(particles=64, lag=4, seed=1)
    params = scene.parameters
    assert set(r["score"]) == set(params)
    for name, g in r["score"].items():
        assert g.shape == params[name].shape and np.all(np.isfinite(g))
    assert np.isfinite(r["loglik"]) and r["rows_evaluated"] > 0
    assert r["particle_slots"] == 64 * 6 * scene.num_objects


def test_seed_reproducible_and_timed(scene):
    a = scene.score(particles=64, lag=4, seed=2)
    b, secs = scene.score_timed(particles=64, lag=4, seed=2)
    assert secs > 0
    for name in a["score"]:
        np.testing.assert_array_equal(a["score"][name], b["score"][name])


def test_baseline_estimators_run(scene):
    for est in ["pf", "dpf-sgr"]:
        r = scene.score(estimator=est, particles=16, lag=4, seed=1)
        assert all(np.all(np.isfinite(g)) for g in r["score"].values())


def test_bad_settings(scene):
    with pytest.raises(ValueError, match="estimator"):
        scene.score(estimator="x")
    with pytest.raises(ValueError, match="transitions: must be at least 1"):
        pfsefi.SyntheticScene(transitions=0)
