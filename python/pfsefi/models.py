"""Reference models written in Python as callbacks (see :class:`pfsefi.Model`).

:class:`LinearGaussianCallbacks` is the built-in linear-Gaussian model written in
NumPy: it maps the noise to states with the same float32 arithmetic as the Rust
model, so on one seed it draws the same particles and gets the same
log-likelihood, and its analytic gradient gives PF-SEFI's score.
"""

import numpy as np

from . import Model

_LN_2PI = float(np.log(2.0 * np.pi))


class LinearGaussianCallbacks(Model):
    """``x_0 ~ N(m0, p0)``, ``x_t = phi x_{t-1} + sv e_t``, ``y_t = x_t + sw u_t``,
    with ``theta = [phi, ln sv, ln sw]`` and a prior free of ``theta``."""

    state_dim = 1
    prior_noise_dim = 1
    transition_noise_dim = 1

    def __init__(self, m0, p0):
        self.m0 = float(m0)
        self.p0 = float(p0)

    def prior(self, theta, z):
        return self.m0 + np.sqrt(self.p0) * z

    def transition(self, theta, t, x_prev, z):
        f32 = np.float32
        phi, sv = f32(theta[0]), f32(np.exp(theta[1]))
        return phi * x_prev.astype(f32) + sv * z.astype(f32)

    def log_observation(self, theta, t, y, x):
        f32 = np.float32
        log_sw = float(theta[2])
        c, inv = f32(-0.5 * _LN_2PI - log_sw), f32(np.exp(-log_sw))
        z = (x[:, 0].astype(f32) - f32(y[0])) * inv
        return c - f32(0.5) * z * z

    def grad_log_density(self, theta, t, y, x_prev, x, w):
        phi, log_sv, log_sw = theta
        x = x[:, 0]
        r = y[:, 0] - x
        g = np.zeros(3)
        g[2] = np.sum(w * (-1.0 + r * r * np.exp(-2.0 * log_sw)))
        if x_prev is not None:
            xp = x_prev[:, 0]
            e = x - phi * xp
            inv_v = np.exp(-2.0 * log_sv)
            g[0] = np.sum(w * e * xp * inv_v)
            g[1] = np.sum(w * (-1.0 + e * e * inv_v))
        return g
