"""Every bad input reaches Python as an exception of a fitting type naming what and where."""

import numpy as np
import pytest

import pfsefi
from pfsefi.models import LinearGaussianCallbacks

MODEL = pfsefi.LinearGaussian(0.7, 0.6, 0.8)
CALLBACKS = LinearGaussianCallbacks(MODEL.m0, MODEL.p0)
Y = MODEL.simulate(20, seed=0)[1][0]


@pytest.mark.parametrize("call", [
    lambda y: MODEL.kalman_loglik(y),
    lambda y: MODEL.score(y, particles=16),
    lambda y: pfsefi.particle_filter(CALLBACKS, y, MODEL.theta, particles=16),
])
class TestArrays:
    def test_integer_dtype_is_a_type_error(self, call):
        with pytest.raises(TypeError, match=r"y: expected a floating-point array.*int64"):
            call(np.arange(10, dtype=np.int64))

    def test_string_array_is_a_type_error(self, call):
        with pytest.raises(TypeError, match=r"^y: "):
            call(np.array(["a", "b"]))

    def test_nan_names_the_entry(self, call):
        y = Y.copy()
        y[7] = np.nan
        with pytest.raises(ValueError, match=r"y: entry \[7\] is NaN"):
            call(y)

    def test_infinity_names_the_entry(self, call):
        y = Y.copy()
        y[3] = np.inf
        with pytest.raises(ValueError, match=r"y: entry \[3\] is inf"):
            call(y)

    def test_empty_array(self, call):
        with pytest.raises(ValueError, match=r"y: the array is empty"):
            call(np.zeros(0))

    def test_wrong_shape(self, call):
        with pytest.raises(ValueError, match=r"y: expected shape"):
            call(np.zeros((2, 3, 4, 5)))


def test_float32_and_lists_are_accepted():
    a = MODEL.kalman_loglik(Y.astype(np.float32))
    b = MODEL.kalman_loglik(list(Y.astype(np.float32)))
    assert a == b


def test_bad_model_parameters():
    with pytest.raises(ValueError, match=r"sv: must be > 0"):
        pfsefi.LinearGaussian(0.5, -1.0, 1.0)
    with pytest.raises(ValueError, match=r"phi.*stationary"):
        pfsefi.LinearGaussian(1.5, 1.0, 1.0)
    with pytest.raises(ValueError, match=r"phi: must be finite"):
        pfsefi.LinearGaussian(float("nan"), 1.0, 1.0)
    with pytest.raises(ValueError, match=r"m0 and p0"):
        pfsefi.LinearGaussian(0.5, 1.0, 1.0, m0=0.0)
    with pytest.raises(ValueError, match=r"theta: expected shape \(3,\)"):
        MODEL.with_theta([1.0, 2.0])


def test_bad_settings():
    with pytest.raises(ValueError, match=r"estimator: .*pf-sefi, pf, dpf-sgr"):
        MODEL.score(Y, estimator="nope")
    with pytest.raises(ValueError, match=r"particles: must be at least 1"):
        MODEL.score(Y, particles=0)
    with pytest.raises(ValueError, match=r"precision"):
        MODEL.score(Y, precision="f16")
    with pytest.raises(ValueError, match=r"resampling"):
        MODEL.score(Y, resampling="stratified")
    with pytest.raises(ValueError, match=r"ess_threshold"):
        MODEL.score(Y, ess_threshold=2.0)
    with pytest.raises(ValueError, match=r"pfnet.alpha"):
        MODEL.score(Y, estimator="pfnet", alpha=0.0)
    with pytest.raises(ValueError, match=r"steps: must be at least 1"):
        MODEL.simulate(0)


def test_callback_exception_is_wrapped_with_its_place():
    class Failing(LinearGaussianCallbacks):
        def transition(self, theta, t, x_prev, z):
            if t == 4:
                raise KeyError("boom")
            return super().transition(theta, t, x_prev, z)

    with pytest.raises(pfsefi.CallbackError, match=r"model.transition raised KeyError.*boom.*object 0, t = 4") as e:
        pfsefi.particle_filter(Failing(MODEL.m0, MODEL.p0), Y, MODEL.theta, particles=16)
    assert isinstance(e.value.__cause__, KeyError)


def test_callback_wrong_shape_and_dtype_and_nan():
    class WrongShape(LinearGaussianCallbacks):
        def log_observation(self, theta, t, y, x):
            return np.zeros(3)

    with pytest.raises(ValueError, match=r"model.log_observation returned shape \[3\] \(object 0, t = 0\); expected \[16\]"):
        pfsefi.particle_filter(WrongShape(MODEL.m0, MODEL.p0), Y, MODEL.theta, particles=16)

    class WrongDtype(LinearGaussianCallbacks):
        def prior(self, theta, z):
            return np.array(["x"] * len(z))

    with pytest.raises(TypeError, match=r"model.prior returned an array of dtype"):
        pfsefi.particle_filter(WrongDtype(MODEL.m0, MODEL.p0), Y, MODEL.theta, particles=16)

    class NanGrad(LinearGaussianCallbacks):
        def grad_log_density(self, theta, t, y, x_prev, x, w):
            return np.full(3, np.nan)

    with pytest.raises(ValueError, match=r"model.grad_log_density returned NaN.*object 0"):
        pfsefi.particle_filter(NanGrad(MODEL.m0, MODEL.p0), Y, MODEL.theta, particles=16)


def test_model_without_methods_or_state_dim():
    class NoDim:
        pass

    with pytest.raises(TypeError, match=r"model: has no attribute \"state_dim\""):
        pfsefi.particle_filter(NoDim(), Y, MODEL.theta)

    class NoGrad:
        state_dim = 1
        prior = transition = log_observation = staticmethod(lambda *a: None)

    with pytest.raises(TypeError, match=r"model: has no method \"grad_log_density\""):
        pfsefi.particle_filter(NoGrad(), Y, MODEL.theta)
    with pytest.raises(ValueError, match=r"theta: expected a vector"):
        pfsefi.particle_filter(CALLBACKS, Y, np.zeros((3, 1)))
