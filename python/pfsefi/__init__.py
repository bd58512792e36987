"""PF-SEFI: particle-filter score estimation with Fisher's identity, for NumPy and JAX users.

The engine is Rust (the ``ssm`` crate); this package calls it with NumPy arrays in
and out and releases the GIL while it computes.

* :class:`LinearGaussian` -- the built-in linear-Gaussian model: simulation, the
  exact Kalman log-likelihood and score, and every particle estimator's score.
* :func:`particle_filter` -- a model written in Python (see :class:`Model`),
  filtered in Rust, with PF-SEFI's score from its callbacks.
* :class:`SyntheticScene` -- the vehicle model on a generated scene: any
  estimator's score as a dict by parameter name.
* :func:`read_params`, :func:`write_params`, :func:`convert_params` -- parameter
  files (``.npz`` or the project's format) as dicts of arrays.
* :class:`Dataset` -- the project's dataset format read and written, built from
  arrays (the CSV files' columns, :data:`COLUMNS`); :func:`generate_experiment`,
  :func:`generate_hidden` and :func:`import_kitti` make one.
* :class:`VehicleModel` -- the vehicle model of a dataset and a parameter file:
  filter and smoother, any estimator's score by parameter name, evaluation
  metrics and training with a progress callback; :func:`diagnose` runs the
  diagnosis and returns its report as a dict.
"""

from ._native import (
    COLUMNS,
    CallbackError,
    DataError,
    Dataset,
    LinearGaussian,
    SyntheticScene,
    VehicleModel,
    convert_params,
    diagnose,
    generate_experiment,
    generate_hidden,
    import_kitti,
    particle_filter,
    read_params,
    write_params,
)

__all__ = [
    "COLUMNS",
    "CallbackError",
    "DataError",
    "Dataset",
    "VehicleModel",
    "diagnose",
    "generate_experiment",
    "generate_hidden",
    "import_kitti",
    "LinearGaussian",
    "Model",
    "SyntheticScene",
    "convert_params",
    "particle_filter",
    "read_params",
    "write_params",
]


class Model:
    """The callbacks of a model written in Python (subclassing is optional).

    :func:`particle_filter` calls them with float64 arrays, one row per particle,
    and ``theta``, the parameter vector it was given (read-only). Rust draws every
    standard-normal ``z`` and runs the filter, resampling, fixed-lag smoothing and
    the sum of the smoothing weights onto distinct ancestors.
    """

    #: Dimension ``d`` of the state.
    state_dim: int = 1
    #: Columns of the noise ``z`` handed to :meth:`prior` (default ``state_dim``).
    prior_noise_dim: int
    #: Columns of the noise ``z`` handed to :meth:`transition` (default ``state_dim``).
    transition_noise_dim: int

    def prior(self, theta, z):
        """``x_0`` of shape ``(n, d)`` from standard-normal ``z`` of shape ``(n, prior_noise_dim)``."""
        raise NotImplementedError

    def transition(self, theta, t, x_prev, z):
        """``x_t`` of shape ``(n, d)`` from ``x_prev`` ``(n, d)`` and standard-normal ``z``."""
        raise NotImplementedError

    def log_observation(self, theta, t, y, x):
        """``log g(y_t | x_t^i)`` of shape ``(n,)``; ``y`` is ``y_t``, shape ``(q,)``."""
        raise NotImplementedError

    def grad_log_density(self, theta, t, y, x_prev, x, w):
        """The gradient in ``theta`` (shape ``(p,)``) of
        ``sum_i w_i [log g(y_i | x_i) + log f(x_i | x_prev_i)]`` over ``R`` rows
        (``t`` ``(R,)`` int64, ``y`` ``(R, q)``, ``x_prev`` and ``x`` ``(R, d)``,
        ``w`` ``(R,)``). ``x_prev`` is ``None`` for the rows at ``t = 0``: there the
        second term is ``log p(x_0)``. With JAX this is one ``jax.grad`` of
        ``jnp.sum(w * logpdf)``.
        """
        raise NotImplementedError
