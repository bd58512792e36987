"""Type stub of the native module ``pfsefi._native`` (Rust, PyO3)."""

import os
from typing import Any, Callable, Dict, List, Mapping, Optional, Protocol, Sequence, Tuple, TypedDict, Union

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

PathLike = Union[str, os.PathLike]

#: Column names of every dataset table (as in its CSV file), by table name:
#: ``av``, ``objects``, ``points``, ``boxes``, ``states``, ``actions``.
COLUMNS: Dict[str, List[str]]

class DataError(ValueError):
    """A dataset file or table is invalid; ``file``, ``line`` (None for a table
    built in memory) and ``column`` say where."""

    file: Optional[str]
    line: Optional[int]
    column: Optional[str]

class Dataset:
    """A dataset of the project's format (scenes, objects, point sets or box
    detections, optional true states and actions), always valid."""

    @staticmethod
    def read(path: PathLike) -> "Dataset": ...
    def write(self, path: PathLike) -> None: ...
    @staticmethod
    def from_arrays(
        dt: float,
        av: ArrayLike,
        objects: ArrayLike,
        points: Optional[ArrayLike] = None,
        boxes: Optional[ArrayLike] = None,
        states: Optional[ArrayLike] = None,
        actions: Optional[ArrayLike] = None,
        prior_from_detection: bool = False,
    ) -> "Dataset":
        """Tables with the columns of :data:`COLUMNS`; exactly one of ``points`` and ``boxes``."""
    def tables(self) -> Dict[str, F64]:
        """Every table as a 2-D array (``Dataset.from_arrays(ds.dt, **ds.tables())`` rebuilds ``ds``)."""
    @property
    def kind(self) -> str: ...
    @property
    def dt(self) -> float: ...
    @property
    def steps(self) -> int: ...
    @property
    def prior_from_detection(self) -> bool: ...
    @property
    def num_scenes(self) -> int: ...
    @property
    def num_objects(self) -> int: ...
    @property
    def num_observations(self) -> int: ...
    @property
    def has_truth(self) -> bool: ...
    @property
    def object_ids(self) -> NDArray[np.int64]:
        """``(scene id, object id)`` per object, shape ``(objects, 2)``."""
    def observations(self, object: int) -> F64:
        """Points: ``(m, 3)`` rows ``(t, x, y)``; boxes: ``(steps, 6)``, NaN where undetected."""
    def truth(self, object: int) -> Optional[F64]:
        """True states ``(steps, 5)``: ``x, y, yaw, v, kappa``."""
    def actions(self, object: int) -> Optional[F64]:
        """True actions ``(steps, 2)``: ``accel, pinch`` (NaN at ``t = 0``)."""
    def select_scenes(self, scenes: Sequence[int]) -> "Dataset": ...
    def select_objects(self, objects: Sequence[int]) -> "Dataset": ...

def generate_experiment(experiment: str = "A", seed: int = 0, quick: bool = False) -> Tuple[Dataset, Dataset, Dict[str, F64]]:
    """``(train, test, true_params)`` of experiment A or B, as ``sefi generate``."""

def generate_hidden(
    effect: str, strength: float = 1.0, boxes: bool = False, scenes: int = 8, objects: int = 6, steps: int = 16,
    seed: int = 0,
) -> Dataset:
    """A dataset with a hidden effect, as ``sefi generate --hidden``."""

def import_kitti(
    root: PathLike, steps: int = 20, stride: int = 1, align: int = 1, gate: float = 2.0,
    sequences: Optional[Sequence[int]] = None, val_sequences: Optional[Sequence[int]] = None,
) -> Tuple[Dataset, Dataset, str]:
    """``(train, val, report)`` from the KITTI tracking folder, as ``sefi import-kitti``."""

class TrackResult(TypedDict):
    loglik: float
    loglik_per_object: F64
    observed_units: NDArray[np.int64]
    collapsed_steps: NDArray[np.int64]
    min_ess: F64
    filtered: F64
    smoothed: F64

class TrainResult(TypedDict):
    model: "VehicleModel"
    final_eval: Dict[str, float]
    evaluations: List[Tuple[int, Dict[str, float]]]
    steps: int
    skipped_steps: int
    seconds: float

class VehicleModel:
    """The vehicle model of a dataset under a parameter file (path or dict of arrays)."""

    def __init__(self, dataset: Dataset, params: Union[PathLike, Mapping[str, ArrayLike]]) -> None: ...
    @staticmethod
    def initial(
        dataset: Dataset, policy: str = "hand-crafted", init_sd: Tuple[float, float] = (1.0, 0.1), seed: int = 0
    ) -> "VehicleModel": ...
    @property
    def parameters(self) -> Dict[str, F64]: ...
    @property
    def dataset(self) -> Dataset: ...
    @property
    def policy(self) -> str: ...
    def on(self, dataset: Dataset) -> "VehicleModel": ...
    def save_params(self, path: PathLike) -> None: ...
    def filter(self, particles: int = 4096, lag: int = 8, seed: int = 0, filter: str = "tempered") -> TrackResult: ...
    def score(
        self, estimator: str = "pf-sefi", particles: int = 1024, lag: int = 8, seed: int = 0, alpha: float = 0.8,
        precision: str = "f32", filter: str = "tempered", chunk_objects: int = 4,
    ) -> VehicleScore: ...
    def evaluate(
        self, particles: int = 4096, lag: int = 8, seed: int = 0, runs: int = 1, filter: str = "tempered"
    ) -> Dict[str, Any]:
        """``{"runs": [...], "summary": {...}, "per_object": {"loglik", "observed_units"}}``."""
    def train(
        self, test: Dataset, epochs: int = 1, lr: float = 0.01, estimator: str = "pf-sefi", particles: int = 256,
        eval_particles: int = 1024, lag: int = 8, alpha: float = 0.8, seed: int = 0, scenes_per_step: int = 1,
        eval_every: int = 0, clip: Optional[float] = None, final_lr: Optional[float] = None,
        filter: str = "tempered", out: Optional[PathLike] = None,
        callback: Optional[Callable[[int, float], Any]] = None,
    ) -> TrainResult: ...

def diagnose(
    dataset: Dataset, out: PathLike, quick: bool = True, seed: int = 0, protocol: Optional[str] = None,
    settings: Optional[Mapping[str, Any]] = None, heldout: Optional[Dataset] = None,
) -> Dict[str, Any]:
    """The diagnosis's report (``report.json``) as a dict."""
