"""Type stub of the native module ``pfsefi._native`` (Rust, PyO3)."""

from typing import Any, Optional, Protocol, Tuple, TypedDict

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]

class CallbackError(RuntimeError):
    """A callback of a Python-defined model raised; the original is ``__cause__``."""

class ScoreResult(TypedDict):
    loglik: float
    score: F64
    rows_evaluated: int
    particle_slots: int
    collapsed_steps: int
    estimator: str

class FilterResult(TypedDict, total=False):
    loglik: float
    score: F64
    rows_evaluated: int
    collapsed_steps: int

class CallbackModel(Protocol):
    state_dim: int
    def prior(self, theta: F64, z: F64) -> ArrayLike: ...
    def transition(self, theta: F64, t: int, x_prev: F64, z: F64) -> ArrayLike: ...
    def log_observation(self, theta: F64, t: int, y: F64, x: F64) -> ArrayLike: ...
    def grad_log_density(
        self, theta: F64, t: NDArray[np.int64], y: F64, x_prev: Optional[F64], x: F64, w: F64
    ) -> ArrayLike: ...

class LinearGaussian:
    """``x_0 ~ N(m0, p0)``, ``x_t = phi x_{t-1} + sv e_t``, ``y_t = x_t + sw u_t``;
    ``theta = [phi, ln sv, ln sw]``. Without ``m0``/``p0``: the stationary prior."""

    def __init__(
        self, phi: float, sv: float, sw: float, m0: Optional[float] = None, p0: Optional[float] = None
    ) -> None: ...
    @property
    def theta(self) -> F64: ...
    @property
    def m0(self) -> float: ...
    @property
    def p0(self) -> float: ...
    def with_theta(self, theta: ArrayLike) -> "LinearGaussian": ...
    def simulate(self, steps: int, objects: int = 1, seed: int = 0) -> Tuple[F64, F64]:
        """``(x, y)``, each ``(objects, steps)``."""
    def kalman_loglik(self, y: ArrayLike) -> float: ...
    def kalman_score(self, y: ArrayLike) -> Tuple[float, F64]: ...
    def kalman_smooth(self, y: ArrayLike) -> Tuple[F64, F64]: ...
    def score(
        self,
        y: ArrayLike,
        estimator: str = "pf-sefi",
        particles: int = 256,
        lag: int = 10,
        seed: int = 0,
        precision: str = "f64",
        alpha: float = 0.5,
        resampling: str = "systematic",
        ess_threshold: Optional[float] = None,
    ) -> ScoreResult:
        """Estimator ``pf-sefi``, ``pf``, ``dpf-sgr``, ``dpf-sgr-stopped`` or ``pfnet``."""

def particle_filter(
    model: CallbackModel,
    y: ArrayLike,
    theta: ArrayLike,
    particles: int = 256,
    lag: int = 10,
    seed: int = 0,
    score: bool = True,
    resampling: str = "systematic",
    ess_threshold: Optional[float] = None,
) -> FilterResult:
    """Filter a Python-defined model in Rust; with ``score``, PF-SEFI's score."""
