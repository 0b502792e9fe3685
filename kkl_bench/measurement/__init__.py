"""How a task observes the state: the sensor, the sampling and the noise law (protocol 7.6).

The protocol's measurement is ``y_k = h(x_k) + v_k`` at every sample with
``v_k ~ N(0, sigma_v^2 I)``. A track task may declare another
:class:`MeasurementModel`:

* a **sensor**, a registered elementwise function ``s`` of the system's output:
  the measurement is ``s(h(x)) + v`` (:data:`sensors`: ``identity``,
  ``saturating``, ``quantized``; plugins add more through the
  ``kkl_bench.sensors`` entry-point group);
* a **sampling**: with ``observe_every = k`` the measurement is present at
  samples ``0, k, 2k, ...`` and NaN in between (scores still use every sample);
* a **noise law** (:class:`NoiseLaw`): Gaussian, Student-t, or Gaussian with a
  fraction of outliers.

:meth:`MeasurementModel.system` gives the model with the sensor in its ``h``
(and ``h_jacobian``), so filters and data generators need no other change;
:meth:`MeasurementModel.log_density` is the exact density a particle filter
weights with, and :attr:`MeasurementModel.variance` the variance a Gaussian
filter uses for ``R``.

The package is what an estimator reads of a task's measurement (``FitContext.measurement``)
and what a sensor plugin subclasses; it imports only the protocol and the registry.
"""

from kkl_bench.measurement.model import (
    MeasurementModel,
    SensedSystem,
    filter_system,
    held,
    with_scale,
)
from kkl_bench.measurement.noise import NOISE_LAWS, NoiseLaw
from kkl_bench.measurement.sensing import FEATURES, Identity, Quantized, Saturating, Sensor, sensors

__all__ = [
    "FEATURES",
    "NOISE_LAWS",
    "Identity",
    "MeasurementModel",
    "NoiseLaw",
    "Quantized",
    "Saturating",
    "SensedSystem",
    "Sensor",
    "filter_system",
    "held",
    "sensors",
    "with_scale",
]
