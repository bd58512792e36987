"""The built-in linear-Gaussian model from Python: simulation, Kalman, every estimator."""

import numpy as np
import pytest

import pfsefi

MODEL = pfsefi.LinearGaussian(0.7, 0.6, 0.8)


def test_simulate_shapes_and_streams():
    x, y = MODEL.simulate(50, objects=3, seed=4)
    assert x.shape == (3, 50) and y.shape == (3, 50)
    assert x.dtype == np.float64
    # Object k has its own stream: the first object is the same when fewer are drawn.
    x1, y1 = MODEL.simulate(50, objects=1, seed=4)
    np.testing.assert_array_equal(y1[0], y[0])
    assert not np.array_equal(y[0], y[1])


def test_theta_and_prior():
    np.testing.assert_allclose(MODEL.theta, [0.7, np.log(0.6), np.log(0.8)])
    # The stationary prior: P0 = sv^2 / (1 - phi^2).
    assert MODEL.p0 == pytest.approx(0.36 / (1 - 0.49))
    m = MODEL.with_theta([0.5, 0.0, 0.0])
    assert m.theta[0] == 0.5 and m.p0 == MODEL.p0


def test_kalman_score_matches_finite_differences():
    _, y = MODEL.simulate(80, seed=1)
    ll, g = MODEL.kalman_score(y[0])
    assert ll == pytest.approx(MODEL.kalman_loglik(y[0]), abs=1e-10)
    h = 1e-6
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        up = MODEL.with_theta(MODEL.theta + e).kalman_loglik(y[0])
        dn = MODEL.with_theta(MODEL.theta - e).kalman_loglik(y[0])
        assert g[k] == pytest.approx((up - dn) / (2 * h), rel=1e-5, abs=1e-6)


def test_kalman_sums_objects():
    _, y = MODEL.simulate(30, objects=2, seed=2)
    total = MODEL.kalman_loglik(y)
    assert total == pytest.approx(MODEL.kalman_loglik(y[0]) + MODEL.kalman_loglik(y[1]), abs=1e-10)


def test_kalman_smooth_shapes():
    _, y = MODEL.simulate(30, seed=2)
    mean, var = MODEL.kalman_smooth(y[0])
    assert mean.shape == (30,) and np.all(var > 0)


@pytest.mark.parametrize("estimator", ["pf-sefi", "pf", "dpf-sgr", "dpf-sgr-stopped", "pfnet"])
def test_every_estimator_runs_and_is_reproducible(estimator):
    _, y = MODEL.simulate(40, objects=2, seed=3)
    a = MODEL.score(y, estimator=estimator, particles=64, seed=5)
    b = MODEL.score(y, estimator=estimator, particles=64, seed=5)
    assert a["estimator"] == estimator
    assert a["score"].shape == (3,) and np.all(np.isfinite(a["score"]))
    np.testing.assert_array_equal(a["score"], b["score"])
    assert a["particle_slots"] == 64 * 40 * 2
    # Every estimator but PFNET (soft resampling) runs the same filter: the same
    # l_hat on one seed.
    ref = MODEL.score(y, estimator="pf-sefi", particles=64, seed=5)
    if estimator == "pfnet":
        assert a["loglik"] != ref["loglik"]
    else:
        assert a["loglik"] == pytest.approx(ref["loglik"], abs=1e-9)


def test_pf_sefi_score_agrees_with_kalman_over_seeds():
    # 24 seeds of PF-SEFI (N = 2048, L = 10) on one T = 100 sequence: the mean
    # score must be within 4 standard errors of the exact Kalman score. Lag 10 at
    # phi = 0.7 leaves a truncation bias far below one standard error (0.7^10 < 0.03);
    # the particle bias is O(T / N): at N = 512 it was about one standard error of
    # 48 seeds (0.2-0.3 on ln sv and ln sw), at N = 2048 below half of one.
    _, y = MODEL.simulate(100, seed=11)
    _, exact = MODEL.kalman_score(y[0])
    runs = np.array([MODEL.score(y[0], particles=2048, lag=10, seed=s)["score"] for s in range(24)])
    mean, se = runs.mean(0), runs.std(0, ddof=1) / np.sqrt(len(runs))
    assert np.all(np.abs(mean - exact) < 4 * se + 1e-9), (mean, exact, se)
    # The filter's l_hat is close to the exact log-likelihood too.
    ll = np.mean([MODEL.score(y[0], particles=512, seed=s)["loglik"] for s in range(4)])
    assert ll == pytest.approx(MODEL.kalman_loglik(y[0]), abs=1.0)
