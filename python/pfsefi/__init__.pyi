from ._native import CallbackError as CallbackError
from ._native import LinearGaussian as LinearGaussian
from ._native import particle_filter as particle_filter
from ._native import CallbackModel as CallbackModel
from ._native import SyntheticScene as SyntheticScene
from ._native import read_params as read_params
from ._native import write_params as write_params
from ._native import convert_params as convert_params
from typing import Optional
import numpy as np
from numpy.typing import NDArray

class Model:
    state_dim: int
    prior_noise_dim: int
    transition_noise_dim: int
    def prior(self, theta: NDArray[np.float64], z: NDArray[np.float64]) -> NDArray[np.float64]: ...
    def transition(self, theta: NDArray[np.float64], t: int, x_prev: NDArray[np.float64], z: NDArray[np.float64]) -> NDArray[np.float64]: ...
    def log_observation(self, theta: NDArray[np.float64], t: int, y: NDArray[np.float64], x: NDArray[np.float64]) -> NDArray[np.float64]: ...
    def grad_log_density(self, theta: NDArray[np.float64], t: NDArray[np.int64], y: NDArray[np.float64], x_prev: Optional[NDArray[np.float64]], x: NDArray[np.float64], w: NDArray[np.float64]) -> NDArray[np.float64]: ...
from ._native import COLUMNS as COLUMNS
from ._native import DataError as DataError
from ._native import Dataset as Dataset
from ._native import VehicleModel as VehicleModel
from ._native import diagnose as diagnose
from ._native import generate_experiment as generate_experiment
from ._native import generate_hidden as generate_hidden
from ._native import import_kitti as import_kitti
