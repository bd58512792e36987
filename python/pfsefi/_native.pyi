"""Type stub of the native module ``pfsefi._native`` (Rust, PyO3)."""

import os
from typing import Any, Dict, Mapping, Optional, Protocol, Tuple, TypedDict, Union

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

class VehicleScore(TypedDict):
    loglik: float
    score: Dict[str, F64]
    observed_units: int
    rows_evaluated: int
    particle_slots: int
    collapsed_steps: int

class SyntheticScene:
    """A synthetic scene of the paper's setting with its true vehicle model."""

    def __init__(self, transitions: int = 25, seed: int = 3) -> None: ...
    @property
    def parameters(self) -> Dict[str, F64]: ...
    @property
    def num_objects(self) -> int: ...
    def score(
        self, estimator: str = "pf-sefi", particles: int = 1024, lag: int = 8, seed: int = 1,
        precision: str = "f32", alpha: float = 0.8,
    ) -> VehicleScore: ...
    def score_timed(
        self, estimator: str = "pf-sefi", particles: int = 1024, lag: int = 8, seed: int = 1,
        precision: str = "f32", alpha: float = 0.8,
    ) -> Tuple[VehicleScore, float]: ...
    def save_params(self, path: Union[str, os.PathLike]) -> None: ...

def read_params(path: Union[str, os.PathLike]) -> Dict[str, F64]:
    """A parameter file (``.npz`` or the project's format) as arrays by name."""

def write_params(params: Mapping[str, ArrayLike], path: Union[str, os.PathLike]) -> None:
    """Arrays by name as a parameter file (``.npz`` or the project's format, by extension)."""

def convert_params(
    src: Union[str, os.PathLike], dst: Union[str, os.PathLike], like: Optional[Union[str, os.PathLike]] = None
) -> None:
    """A parameter file converted between formats by extension."""
