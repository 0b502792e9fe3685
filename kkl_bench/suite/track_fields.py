"""The fields of a track file that are more than a number or a name: where initial states
come from (:class:`X0Box`), the plant that makes the data (:class:`Plant`) and the
measurement model, each parsed with an error naming the field (:class:`TrackError`).
:mod:`kkl_bench.suite.tracks` reads the files."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from kkl_bench.measurement import NOISE_LAWS, MeasurementModel, NoiseLaw, sensors
from kkl_bench.registry import systems


class TrackError(ValueError):
    """A track file is malformed; the message names the file, the task and the field."""


@dataclass(frozen=True)
class X0Box:
    """Where initial states are drawn from: the system's box with its half-widths times
    ``scale`` about its centre, or an explicit ``(system, low, high)`` box."""

    scale: float = 1.0
    explicit: tuple[tuple[str, tuple[float, ...], tuple[float, ...]], ...] = ()

    def for_system(self, system: Any) -> tuple[np.ndarray, np.ndarray]:
        """``(low, high)``, each ``(n_x,)``, for the system model ``system``."""
        for name, low, high in self.explicit:
            if name == system.name:
                return np.array(low), np.array(high)
        if self.scale == 1.0:
            return system.x0_low, system.x0_high
        centre = (system.x0_low + system.x0_high) / 2.0
        half = self.scale * (system.x0_high - system.x0_low) / 2.0
        return centre - half, centre + half


@dataclass(frozen=True)
class Plant:
    """How the plant that makes a task's data differs from the nominal model every
    estimator is given (protocol section 7.5; :mod:`kkl_bench.suite.plants` builds it).

    Attributes
    ----------
    parameters: relative parameter error; each physical parameter of the system is
        multiplied by ``1 + parameters`` or ``1 - parameters``, the sign drawn once per
        parameter from the track's pinned plant stream.
    sensor_gain, sensor_offset: the plant measures ``sensor_gain h(x) + sensor_offset``
        (plus the noise) where the model says ``h(x)``.
    """

    parameters: float = 0.0
    sensor_gain: float = 1.0
    sensor_offset: float = 0.0

    @property
    def nominal(self) -> bool:
        """Whether this is the nominal model itself (every track but ``mismatch``)."""
        return self == Plant()

    @property
    def key(self) -> str:
        """The plant's name in stream keys, e.g. ``plant-p0.25-g1-o0``."""
        return f"plant-p{self.parameters:g}-g{self.sensor_gain:g}-o{self.sensor_offset:g}"


def parse_number(field: str, value: Any, positive: bool = False, signed: bool = False) -> float:
    if not isinstance(value, int | float) or isinstance(value, bool) or not np.isfinite(value):
        raise TrackError(f"field {field!r} must be a number, got {value!r}")
    if (value < 0 and not signed) or (positive and value == 0):
        raise TrackError(
            f"field {field!r} must be {'positive' if positive else 'non-negative'}, got {value!r}"
        )
    return float(value)


_MEASUREMENT_FIELDS = (
    "sensor",
    "observe_every",
    "noise",
    "dof",
    "outlier_fraction",
    "outlier_scale",
)


def parse_measurement(value: Any, sigma_v: float) -> MeasurementModel:
    """The task's measurement model from its ``measurement`` table (noise scale ``sigma_v``)."""
    if not isinstance(value, dict):
        raise TrackError(f"field 'measurement' must be a table, got {value!r}")
    name = value.get("sensor", "identity")
    if not isinstance(name, str) or name not in sensors:
        raise TrackError(
            f"field 'measurement.sensor': unknown sensor {name!r}; valid sensors: "
            f"{', '.join(sensors.names())}"
        )
    sensor_class = sensors.get(name)
    sensor_fields = [f.name for f in dataclasses.fields(sensor_class)]
    sensor_params = {key: v for key, v in value.items() if key not in _MEASUREMENT_FIELDS}
    unknown = sorted(set(sensor_params) - set(sensor_fields))
    if unknown:
        raise TrackError(
            f"unknown field 'measurement.{unknown[0]}'; valid: "
            f"{', '.join([*_MEASUREMENT_FIELDS, *sensor_fields])} (sensor {name!r} takes "
            f"{', '.join(sensor_fields) or 'no parameters'})"
        )
    law = value.get("noise", "gaussian")
    if law not in NOISE_LAWS:
        raise TrackError(
            f"field 'measurement.noise': unknown law {law!r}; valid laws: {', '.join(NOISE_LAWS)}"
        )
    law_params = {
        key: parse_number(f"measurement.{key}", value[key])
        for key in ("dof", "outlier_fraction", "outlier_scale")
        if key in value
    }
    every = value.get("observe_every", 1)
    if not isinstance(every, int) or isinstance(every, bool) or every < 1:
        raise TrackError(
            f"field 'measurement.observe_every' must be a positive integer, got {every!r}"
        )
    try:
        sensor = sensor_class(
            **{key: parse_number(f"measurement.{key}", v) for key, v in sensor_params.items()}
        )
        return MeasurementModel(sensor, every, NoiseLaw(law, sigma_v, **law_params))
    except ValueError as error:
        raise TrackError(f"field 'measurement': {error}") from None


def parse_plant(value: Any) -> Plant:
    if not isinstance(value, dict):
        raise TrackError(f"field 'plant' must be a table, got {value!r}")
    fields = [f.name for f in dataclasses.fields(Plant)]
    unknown = sorted(set(value) - set(fields))
    if unknown:
        raise TrackError(f"unknown field 'plant.{unknown[0]}'; valid: {', '.join(fields)}")
    plant = Plant(
        **{
            key: parse_number(f"plant.{key}", value[key], signed=key == "sensor_offset")
            for key in value
        }
    )
    if plant.parameters >= 1.0:
        raise TrackError(f"field 'plant.parameters' must be below 1, got {plant.parameters!r}")
    if plant.sensor_gain == 0.0:
        raise TrackError("field 'plant.sensor_gain' must not be 0")
    return plant


def parse_x0_box(value: Any, track_systems: tuple[str, ...]) -> X0Box:
    if not isinstance(value, dict):
        raise TrackError(f"field 'x0_box' must be a table, got {value!r}")
    scale = parse_number("x0_box.scale", value.get("scale", 1.0), positive=True)
    explicit = []
    for system, box in value.items():
        if system == "scale":
            continue
        if system not in track_systems:
            raise TrackError(
                f"field 'x0_box.{system}': not a system of this track ({', '.join(track_systems)})"
            )
        n_x = systems.get(system)().n_x
        if not isinstance(box, dict) or set(box) != {"low", "high"}:
            raise TrackError(f"field 'x0_box.{system}' must set exactly low and high")
        low, high = (np.asarray(box[k], dtype=float) for k in ("low", "high"))
        if low.shape != (n_x,) or high.shape != (n_x,) or np.any(low > high):
            raise TrackError(
                f"field 'x0_box.{system}': low and high must be {n_x} numbers with low <= high, "
                f"got {box['low']!r} and {box['high']!r}"
            )
        explicit.append((system, tuple(low.tolist()), tuple(high.tolist())))
    return X0Box(scale, tuple(explicit))
