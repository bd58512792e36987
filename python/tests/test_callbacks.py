"""A model written in Python: the linear-Gaussian model as callbacks against the built-in one."""

import numpy as np
import pytest

import pfsefi
from pfsefi.models import LinearGaussianCallbacks

MODEL = pfsefi.LinearGaussian(0.7, 0.6, 0.8)
CALLBACKS = LinearGaussianCallbacks(MODEL.m0, MODEL.p0)


def test_same_loglik_as_builtin_for_the_same_seed():
    _, y = MODEL.simulate(60, objects=3, seed=7)
    for seed in range(3):
        builtin = MODEL.score(y, particles=128, seed=seed)
        ours = pfsefi.particle_filter(CALLBACKS, y[:, :, None], MODEL.theta, particles=128, seed=seed, score=False)
        # The callbacks repeat the Rust model's float32 arithmetic on the same noise,
        # so the particles are the same and l_hat agrees to rounding.
        assert ours["loglik"] == pytest.approx(builtin["loglik"], rel=1e-9, abs=1e-9)
    # A different seed gives a different l_hat (the seed reaches the filter).
    other = pfsefi.particle_filter(CALLBACKS, y[:, :, None], MODEL.theta, particles=128, seed=99, score=False)
    assert other["loglik"] != pytest.approx(builtin["loglik"], abs=1e-9)


def test_same_pf_sefi_score_as_builtin_for_the_same_seed():
    _, y = MODEL.simulate(60, seed=8)
    builtin = MODEL.score(y[0], particles=128, lag=5, seed=3, precision="f64")
    ours = pfsefi.particle_filter(CALLBACKS, y[0], MODEL.theta, particles=128, lag=5, seed=3)
    assert ours["rows_evaluated"] == builtin["rows_evaluated"]
    np.testing.assert_allclose(ours["score"], builtin["score"], rtol=1e-6, atol=1e-6)


def test_pf_sefi_score_of_callbacks_agrees_with_kalman_over_seeds():
    # 24 seeds, N = 2048, L = 10, T = 100: the mean PF-SEFI score of the Python-defined
    # model is within 4 standard errors of the exact Kalman score (the tolerance as in
    # test_lgssm.test_pf_sefi_score_agrees_with_kalman_over_seeds).
    _, y = MODEL.simulate(100, seed=11)
    _, exact = MODEL.kalman_score(y[0])
    runs = np.array(
        [pfsefi.particle_filter(CALLBACKS, y[0], MODEL.theta, particles=2048, lag=10, seed=s)["score"] for s in range(24)]
    )
    mean, se = runs.mean(0), runs.std(0, ddof=1) / np.sqrt(len(runs))
    assert np.all(np.abs(mean - exact) < 4 * se + 1e-9), (mean, exact, se)


def test_score_is_not_gradient_of_a_wrong_model():
    # The test above must be able to fail: a model whose gradient drops the
    # transition's terms gives a score far from Kalman's.
    class Broken(LinearGaussianCallbacks):
        def grad_log_density(self, theta, t, y, x_prev, x, w):
            g = super().grad_log_density(theta, t, y, x_prev, x, w)
            g[:2] = 0.0
            return g

    _, y = MODEL.simulate(100, seed=11)
    _, exact = MODEL.kalman_score(y[0])
    g = pfsefi.particle_filter(Broken(MODEL.m0, MODEL.p0), y[0], MODEL.theta, particles=512, seed=0)["score"]
    assert abs(g[0] - exact[0]) > 5.0


def test_multidimensional_state_and_noise_layout():
    # Two independent copies of the model as one 2-d state: the score of the pair
    # is the sum of both scores with a shared theta.
    class Pair(pfsefi.Model):
        state_dim = 2

        def prior(self, theta, z):
            return CALLBACKS.m0 + np.sqrt(CALLBACKS.p0) * z

        def transition(self, theta, t, x_prev, z):
            return theta[0] * x_prev + np.exp(theta[1]) * z

        def log_observation(self, theta, t, y, x):
            r = (y[None, :] - x) * np.exp(-theta[2])
            return np.sum(-0.5 * np.log(2 * np.pi) - theta[2] - 0.5 * r * r, axis=1)

        def grad_log_density(self, theta, t, y, x_prev, x, w):
            g = np.zeros(3)
            r = y - x
            g[2] = np.sum(w[:, None] * (-1.0 + r * r * np.exp(-2 * theta[2])))
            if x_prev is not None:
                e = x - theta[0] * x_prev
                g[0] = np.sum(w[:, None] * e * x_prev) * np.exp(-2 * theta[1])
                g[1] = np.sum(w[:, None] * (-1.0 + e * e * np.exp(-2 * theta[1])))
            return g

    _, y = MODEL.simulate(40, objects=2, seed=5)
    pair = np.stack([y[0], y[1]], axis=1)  # (steps, 2)
    r = pfsefi.particle_filter(Pair(), pair, MODEL.theta, particles=256, seed=1)
    assert r["score"].shape == (3,)
    ll_exact = MODEL.kalman_loglik(y)
    assert r["loglik"] == pytest.approx(ll_exact, abs=3.0)
