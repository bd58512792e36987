"""Learn a stochastic-volatility model -- a model the project does not ship -- written
in Python as callbacks, with PF-SEFI's score computed in Rust.

    x_0 ~ N(0, sigma^2 / (1 - phi^2)),  x_t = phi x_{t-1} + sigma e_t,
    y_t = beta exp(x_t / 2) u_t,        theta = [phi, ln sigma, ln beta].

From a wrong start the parameters are learned by Adam on the PF-SEFI score, and
the held-out log-likelihood is reported; the learning curve is plotted with
matplotlib when it is installed.

    python examples/python/stochastic_volatility.py [--iterations 150] [--plot sv.png]
"""

import argparse
import time

import numpy as np

import pfsefi

LN_2PI = float(np.log(2.0 * np.pi))
TRUTH = np.array([0.9, np.log(0.4), np.log(0.7)])
START = np.array([0.3, np.log(1.2), np.log(2.0)])


class StochasticVolatility(pfsefi.Model):
    """The model's callbacks; the prior is the stationary law, so it depends on theta."""

    state_dim = 1

    def prior(self, theta, z):
        phi, sigma = theta[0], np.exp(theta[1])
        return z * sigma / np.sqrt(1.0 - phi * phi)

    def transition(self, theta, t, x_prev, z):
        return theta[0] * x_prev + np.exp(theta[1]) * z

    def log_observation(self, theta, t, y, x):
        x = x[:, 0]
        log_beta = theta[2]
        return -0.5 * LN_2PI - log_beta - 0.5 * x - 0.5 * y[0] ** 2 * np.exp(-x - 2.0 * log_beta)

    def grad_log_density(self, theta, t, y, x_prev, x, w):
        phi, log_sigma, log_beta = theta
        x, y = x[:, 0], y[:, 0]
        g = np.zeros(3)
        g[2] = np.sum(w * (-1.0 + y * y * np.exp(-x - 2.0 * log_beta)))
        if x_prev is None:
            # log N(x; 0, v) with ln v = 2 ln sigma - ln(1 - phi^2).
            v = np.exp(2.0 * log_sigma) / (1.0 - phi * phi)
            d_lnv = np.sum(w * (-0.5 + 0.5 * x * x / v))
            g[0] += d_lnv * 2.0 * phi / (1.0 - phi * phi)
            g[1] += d_lnv * 2.0
        else:
            xp = x_prev[:, 0]
            e = x - phi * xp
            inv = np.exp(-2.0 * log_sigma)
            g[0] += np.sum(w * e * xp * inv)
            g[1] += np.sum(w * (-1.0 + e * e * inv))
        return g


def simulate(theta, objects, steps, seed):
    """`objects` sequences of `steps` observations, shape (objects, steps, 1)."""
    rng = np.random.default_rng(seed)
    phi, sigma, beta = theta[0], np.exp(theta[1]), np.exp(theta[2])
    x = rng.standard_normal(objects) * sigma / np.sqrt(1 - phi * phi)
    ys = np.empty((objects, steps))
    for t in range(steps):
        if t > 0:
            x = phi * x + sigma * rng.standard_normal(objects)
        ys[:, t] = beta * np.exp(x / 2) * rng.standard_normal(objects)
    return ys[:, :, None]


def learn(iterations=150, objects=16, steps=100, particles=256, lag=10, lr=0.05, seed=0, log=print):
    """Adam on the PF-SEFI score (per observation) from START. Returns the history:
    a list of (iteration, theta, held-out log-likelihood per observation)."""
    model = StochasticVolatility()
    train = simulate(TRUTH, objects, steps, seed)
    test = simulate(TRUTH, objects, steps, seed + 1)
    n_obs = objects * steps

    def test_loglik(theta, it):
        r = pfsefi.particle_filter(model, test, theta, particles=particles, seed=10_000 + it, score=False)
        return r["loglik"] / n_obs

    theta = START.copy()
    m, v = np.zeros(3), np.zeros(3)
    history = [(0, theta.copy(), test_loglik(theta, 0))]
    log(f"start  theta = {np.round(theta, 3)}  held-out loglik/obs = {history[0][2]:.4f}")
    for it in range(1, iterations + 1):
        g = pfsefi.particle_filter(model, train, theta, particles=particles, lag=lag, seed=it)["score"] / n_obs
        m = 0.9 * m + 0.1 * g
        v = 0.999 * v + 0.001 * g * g
        step = lr * (m / (1 - 0.9**it)) / (np.sqrt(v / (1 - 0.999**it)) + 1e-8)
        theta = theta + step
        theta[0] = np.clip(theta[0], -0.99, 0.99)
        if it % 10 == 0 or it == iterations:
            history.append((it, theta.copy(), test_loglik(theta, it)))
            log(f"iter {it:4d}  theta = {np.round(theta, 3)}  held-out loglik/obs = {history[-1][2]:.4f}")
    return history


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--iterations", type=int, default=150)
    ap.add_argument("--plot", default="stochastic_volatility.png", help="where to save the learning curve")
    args = ap.parse_args()
    t0 = time.perf_counter()
    history = learn(args.iterations)
    theta = history[-1][1]
    print(f"truth  theta = {np.round(TRUTH, 3)}  (phi, ln sigma, ln beta)")
    print(f"learned phi = {theta[0]:.3f} (true 0.9), sigma = {np.exp(theta[1]):.3f} (0.4), "
          f"beta = {np.exp(theta[2]):.3f} (0.7) in {time.perf_counter() - t0:.1f} s")
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is not installed: no plot")
        return
    its = [h[0] for h in history]
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.5))
    a.plot(its, [h[2] for h in history], marker="o")
    a.set_xlabel("iteration")
    a.set_ylabel("held-out log-likelihood per observation")
    for k, (name, f, true) in enumerate([("phi", lambda x: x, 0.9), ("sigma", np.exp, 0.4), ("beta", np.exp, 0.7)]):
        line = b.plot(its, [f(h[1][k]) for h in history], label=name)[0]
        b.axhline(true, color=line.get_color(), linestyle="--", linewidth=0.8)
    b.set_xlabel("iteration")
    b.legend()
    b.set_title("parameters (dashed: truth)")
    fig.tight_layout()
    fig.savefig(args.plot, dpi=100)
    print(f"learning curve: {args.plot}")


if __name__ == "__main__":
    main()
