"""Calibrating the nominal model on logged data: what an estimation engineer does first.

On the ``mismatch`` track an estimator that uses logged data receives 100
trajectories logged on the true plant, with their states (protocol section 7.5).
The model-based filters use them the classical way: keep the nominal model's
structure, fit its physical parameters and the sensor's gain and offset by
least squares, and filter with the calibrated model (rows ``ekf+logged``, ...);
the KKL observers train on data the calibrated model simulates
(:meth:`kkl_bench.training.TrainingData.with_system`).

The loss (:func:`calibrate`) has two blocks of residuals, each scaled by its
noise level so that both weigh as what they are, standardized errors:

* one-step state residuals ``(x_{k+1} - RK4_theta(x_k, u_k)) / sigma_w`` over every
  logged step, but for the state components that start within
  :data:`CONSTRAINT_MARGIN` deviations of the system's constraint (erratum E1:
  Rossler's ``x3``, reflected at 0), whose next value may be folded: with the
  states known, this is the maximum-likelihood fit of
  ``theta`` under the protocol's Gaussian process noise, and it is well posed
  for every parameter the dynamics depend on (a multi-step or output-only loss
  would be non-convex on the chaotic systems);
* output residuals ``(y_k - (gain h(x_k) + offset)) / sigma_v``, the
  maximum-likelihood fit of the sensor.

``scipy.optimize.least_squares`` (trust-region reflective) starts from the
nominal values, with every parameter in ``[0, 2]`` times nominal, the gain in
``[0.5, 2]`` and the offset in ``[-1, 1]``. Parameters that the system's
constructor does not take (Lorenz-96's dimension) stay as they are. The true
plant's parameters are never read; the conformance kit seals them while the
estimator fits.
"""

from __future__ import annotations

import dataclasses
import inspect

import numba
import numpy as np
from scipy.optimize import least_squares

from kkl_bench.estimator import FitContext
from kkl_bench.protocol import compiled
from kkl_bench.protocol.simulate import Trajectories, rk4_step
from kkl_bench.protocol.system import ReadThrough, System

CONSTRAINT_MARGIN = 30.0
"""A state component within this many process-noise deviations of where the system's
constraint acts (Rossler's ``x3`` near 0) gives no one-step residual: its next value
may have been reflected, which biases a least-squares fit (Rossler's ``b`` by +50 %)."""


class CalibratedSystem(ReadThrough):
    """``model`` (a system with fitted parameters) read by the sensor
    ``y = gain h(x) + offset``; everything else is ``model``'s."""

    def __init__(self, model: System, gain: float, offset: float) -> None:
        super().__init__(model)
        self.gain, self.offset = gain, offset

    def h(self, x):
        return self.gain * self.model.h(x) + self.offset

    def h_jacobian(self, x):
        return self.gain * self.model.h_jacobian(x)

    def params(self):
        return {**self.model.params(), "sensor_gain": self.gain, "sensor_offset": self.offset}

    def compiled(self):
        """The model's compiled form read by the affine sensor (None if the model has no
        compiled form, or already reads through a sensor of its own)."""
        model = self.model.compiled()
        if model is None or model.sense is not compiled.no_sensor:
            return None
        s = np.array([self.gain, self.offset])
        return dataclasses.replace(model, sense=_affine, sense_slope=_affine_slope, s=s)


@numba.njit(cache=True)
def _affine(h, s):
    for i in range(h.shape[0]):
        for j in range(h.shape[1]):
            h[i, j] = s[0] * h[i, j] + s[1]


@numba.njit(cache=True)
def _affine_slope(h, s, out):
    out[:, :] = s[0]


def calibrate(
    system: System, logged: Trajectories, sigma_w: float, sigma_v: float
) -> CalibratedSystem:
    """``system``'s structure with its parameters and a sensor gain and offset fitted to
    ``logged`` (states, inputs and measurements) by least squares (see the module)."""
    keywords = inspect.signature(type(system).__init__).parameters
    nominal = {name: value for name, value in system.params().items() if name in keywords}
    names = list(nominal)
    start = np.array([*nominal.values(), 1.0, 0.0])
    scale = np.abs(start[:-2])
    low = np.concatenate([start[:-2] - scale, [0.5, -1.0]])
    high = np.concatenate([start[:-2] + scale, [2.0, 1.0]])
    x, u, y = logged.x, logged.u[..., 0], logged.y
    dt = float(logged.t[1] - logged.t[0])
    lowered = x[:, :-1] - CONSTRAINT_MARGIN * sigma_w
    free = system.constrain(lowered) == lowered  # components the constraint cannot touch

    def model(theta):
        return type(system)(**dict(zip(names, theta[:-2], strict=True)))

    def residuals(theta):
        fitted = model(theta)
        step = rk4_step(fitted, x[:, :-1], u[:, :-1], dt)
        dynamics = np.where(free, x[:, 1:] - step, 0.0) / sigma_w
        output = (y - (theta[-2] * system.h(x) + theta[-1])) / sigma_v
        return np.concatenate([dynamics.ravel(), output.ravel()])

    solution = least_squares(
        residuals, start, bounds=(low, high), x_scale=np.maximum(np.abs(start), 0.1)
    )
    return CalibratedSystem(model(solution.x), float(solution.x[-2]), float(solution.x[-1]))


def calibrated_context(context: FitContext) -> FitContext:
    """``context`` with its system calibrated on its logged data, and its training
    generator simulating the calibrated system; unchanged without logged data."""
    if context.logged_data is None:
        return context
    fitted = calibrate(context.system, context.logged_data, context.sigma_w, context.sigma_v)
    return dataclasses.replace(
        context, system=fitted, training=context.training.with_system(fitted)
    )


def calibration_report(context: FitContext) -> dict:
    """The fitted parameters of a calibrated context, for the fit report (empty otherwise)."""
    if not isinstance(context.system, CalibratedSystem):
        return {}
    return {"calibration": context.system.params()}


class CalibratesOnLoggedData:
    """Mixin of the model-based estimators: given logged data (a ``+logged`` row of the
    ``mismatch`` track), fit on the calibrated model, and report what was fitted."""

    uses_logged_data = True

    def fit(self, context: FitContext):
        return super().fit(calibrated_context(context))

    def fit_report(self) -> dict:
        return {**super().fit_report(), **calibration_report(self.check_fitted())}
