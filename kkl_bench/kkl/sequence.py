"""Sequence observers trained by truncated backpropagation through time.

What the learned observers that read the measurement history share
(``gru_observer``, ``kalmannet``): a network ``(y, u) -> x_hat`` that keeps a
state from ``t = 0``, trained on the training families' trajectories in
sweeps of consecutive windows, cached and checkpointed like the KKL models,
and, on the ``mismatch`` track, fine-tuned on a true plant's logged data.

A network here is an ``nn.Module`` with

- ``set_normalization(yu, x)``: fix its input and output scalings from
  training data ``yu: (n, steps, n_y + 1)``, ``x: (n, steps, n_x)``;
- ``normalized(yu, state) -> (out, state)``: standardized estimates
  ``(batch, steps, n_x)`` (``(x_hat - out_mean) / out_scale``) and its final
  state (a tensor or a tuple of tensors; None starts at ``t = 0``);
- ``forward(yu, state) -> (x_hat, state)`` in physical units;
- buffers ``out_mean``, ``out_scale``: ``(n_x,)``;
- ``observed_channel``: whether ``yu`` ends with the channel marking the
  measured samples (:func:`inputs`; True when the task's sampling is sparse).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np
import torch
from torch import nn

from kkl_bench.estimator import FitContext
from kkl_bench.kkl.config import from_budget
from kkl_bench.kkl.gain import simulate_families
from kkl_bench.kkl.optimize import Training, minimize
from kkl_bench.kkl.phase2 import load_or_train
from kkl_bench.kkl.plateau import PlateauRule
from kkl_bench.measurement import held
from kkl_bench.protocol import PROTOCOL_ID
from kkl_bench.protocol.metrics import rmse
from kkl_bench.protocol.system import System
from kkl_bench.registry import regimes
from kkl_bench.support.devices import to_numpy
from kkl_bench.training import FORCED_TRAINING


@dataclass(frozen=True)
class RecurrentConfig:
    """The training budget (read with :func:`kkl_bench.kkl.config.from_budget`)."""

    rnn_hidden: int = 64
    rnn_layers: int = 2
    rnn_trajectories: int = 128
    """Training trajectories of each kind (unforced, forced)."""
    rnn_validation: int = 32
    """Validation trajectories of each kind (a separate training stream). The error of a
    recurrent network moves by up to a fifth between two measurements 200 steps apart;
    more trajectories make the best of them less a matter of luck."""
    rnn_steps: int = 16000
    """The cap of Adam steps (the plateau rule ends the training)."""
    rnn_batch: int = 32
    rnn_window: int = 200
    """Samples one step backpropagates through."""
    rnn_lr: float = 3e-3


@dataclass(frozen=True)
class LoggedTuningConfig:
    """The fine-tuning budget on a true plant's logged data (``mismatch`` track only)."""

    rnn_logged_steps: int = 1000
    """The cap of the fine-tuning's Adam steps."""
    rnn_logged_lr: float = 1e-3


HELD_OUT_EVERY = 5
"""Every fifth logged trajectory is held out to validate the fine-tuning."""


def inputs(y: np.ndarray, u: np.ndarray, observed_channel: bool) -> torch.Tensor:
    """Float32 network inputs ``(batch, steps, n_y + 1)`` from ``y`` and ``u``: the last
    measurement held where ``y`` is NaN (:func:`~kkl_bench.measurement.held`) and ``u``;
    with ``observed_channel``, a last channel (``n_y + 2`` in all) that is 1 at the
    samples measured and 0 where the measurement was held."""
    parts = [held(y), u]
    if observed_channel:
        parts.append(~np.isnan(y[..., :1]))
    return torch.as_tensor(np.concatenate(parts, axis=-1), dtype=torch.float32)


def estimates(network: nn.Module, y: np.ndarray, u: np.ndarray) -> np.ndarray:
    """A trained sequence network's estimates ``(batch, steps, n_x)`` (float64) from
    ``y: (batch, steps, n_y)`` (NaN where not measured) and ``u: (batch, steps, 1)``,
    from ``t = 0``."""
    with torch.inference_mode():
        x_hat, _ = network(inputs(y, u, network.observed_channel))
    return x_hat.double().numpy()


def train_windows(
    network: nn.Module,
    yu: torch.Tensor,
    x: torch.Tensor,
    config: RecurrentConfig,
    seed: int,
    label: str,
    validation: Callable[[], float],
    rule: PlateauRule,
) -> Training:
    """Truncated BPTT over ``yu: (n, steps, n_in)`` against ``x: (n, steps, n_x)`` for at
    most ``config.rnn_steps`` steps, ended by the plateau ``rule`` on ``validation()``
    (:func:`~kkl_bench.kkl.optimize.minimize`).

    Training runs in sweeps: a sweep draws ``rnn_batch`` trajectories
    (a function of ``seed`` and the sweep's number only) and walks them from
    ``t = 0`` in consecutive windows of ``rnn_window`` samples, one Adam step
    per window, carrying the hidden state (detached) from window to window as
    at test time. A run resumed in the middle of a sweep rebuilds the carried
    state without gradients.
    """
    target = (x - network.out_mean) / network.out_scale
    count, steps = yu.shape[:2]
    window = min(config.rnn_window, steps)
    per_sweep = steps // window
    carried = {"sweep": None, "rows": None, "state": None}

    def loss(step):
        sweep, position = divmod(step, per_sweep)
        start = position * window
        if carried["sweep"] != sweep:  # a new sweep, or resumed inside one
            choice = np.random.default_rng([seed, sweep]).choice(count, config.rnn_batch)
            carried.update(sweep=sweep, rows=torch.as_tensor(choice), state=None)
            if start:
                with torch.no_grad():
                    carried["state"] = network.normalized(yu[carried["rows"], :start])[1]
        rows = carried["rows"]
        out, state = network.normalized(yu[rows, start : start + window], carried["state"])
        carried["state"] = (
            tuple(s.detach() for s in state) if isinstance(state, tuple) else state.detach()
        )
        return (out - target[rows, start : start + window]).pow(2).sum(-1).mean()

    return minimize(
        loss,
        network.parameters(),
        config.rnn_steps,
        config.rnn_batch * window,
        lr=config.rnn_lr,
        description=label,
        validation=validation,
        rule=rule,
    )


def _train_nominal(
    context: FitContext, network: nn.Module, config, rule: PlateauRule, description
) -> dict:
    """Train ``network`` on the training families; the training log with its validation
    curve (RMSE on validation trajectories of their own stream) and the RMSE of the state
    kept."""
    families = {"unforced": regimes.get("zero")(), "forced": FORCED_TRAINING}
    x, y, u = simulate_families(context, families, config.rnn_trajectories, "rnn/train")
    yu, x = inputs(y, u, network.observed_channel), torch.as_tensor(x, dtype=torch.float32)
    network.set_normalization(yu, x)
    x_val, y_val, u_val = simulate_families(
        context, families, config.rnn_validation, "rnn/validation"
    )
    training = train_windows(
        network,
        yu,
        x,
        config,
        context.seed,
        f"{context.system.name}: {description['kind']}",
        lambda: _validation_rmse(network, y_val, u_val, x_val),
        rule,
    )
    return {**training.log(last=100), "validation_rmse": training.kept_error}


def _validation_rmse(network: nn.Module, y, u, x) -> float:
    """Mean RMSE of ``network`` on ``y, u: (n, steps, .)`` against ``x: (n, steps, n_x)``."""
    with torch.no_grad():
        x_hat, _ = network(inputs(y, u, network.observed_channel))
    return float(rmse(x, to_numpy(x_hat)).mean())


def _fine_tune(
    context: FitContext,
    network: nn.Module,
    config: RecurrentConfig,
    budget: LoggedTuningConfig,
    rule: PlateauRule,
    description: dict[str, Any],
) -> dict:
    """Fine-tune ``network`` on the logged data with ``budget``'s cap and learning rate,
    under the plateau ``rule`` on the held-out logged trajectories; keep it only if their
    RMSE improves."""
    logged = context.logged_data
    held_out = np.arange(len(logged)) % HELD_OUT_EVERY == HELD_OUT_EVERY - 1
    before = _validation_rmse(network, logged.y[held_out], logged.u[held_out], logged.x[held_out])
    nominal = {key: value.clone() for key, value in network.state_dict().items()}
    network.requires_grad_(True)
    tuning = replace(config, rnn_steps=budget.rnn_logged_steps, rnn_lr=budget.rnn_logged_lr)
    training = train_windows(
        network,
        inputs(logged.y[~held_out], logged.u[~held_out], network.observed_channel),
        torch.as_tensor(logged.x[~held_out], dtype=torch.float32),
        tuning,
        context.seed,
        f"{context.system.name}: {description['kind']} on logged data",
        lambda: _validation_rmse(
            network, logged.y[held_out], logged.u[held_out], logged.x[held_out]
        ),
        rule,
    )
    after = training.kept_error
    if after >= before:
        network.load_state_dict(nominal)
    return {
        **training.log(last=100),
        "held_out_rmse_nominal": before,
        "held_out_rmse_fine_tuned": after,
        "fine_tuned": after < before,
    }


def model_description(kind: str, version: int, system: System, seed: int, **extra) -> dict:
    """The cache description of a sequence network of ``kind`` (its module's ``version``)
    trained for ``system`` with ``seed``; ``extra`` adds the plugin's own settings."""
    return {
        "kind": kind,
        "version": version,
        "protocol": PROTOCOL_ID,
        "system": system.name,
        "system_params": system.params(),
        "seed": seed,
        **extra,
    }


def fit_sequence_model(
    context: FitContext, network: nn.Module, config: RecurrentConfig, description: dict[str, Any]
) -> dict[str, Any]:
    """Train ``network`` (or load it from the cache under ``description``) on the training
    families, then, if the context has logged data, fine-tune it on them (cached under
    ``description`` plus their fingerprint). Returns the fit report: the training log
    (and the fine-tuning's), with the optimizer steps and samples each spent."""
    rule = from_budget(PlateauRule, context)
    description = {
        **description,
        "config": asdict(config),
        "plateau": asdict(rule),
        **context.measurement.cache_entry(),
    }
    log = load_or_train(
        context,
        description,
        network,
        lambda _: _train_nominal(context, network, config, rule, description),
    )
    # no Phase 1: the network's own training is its second phase in the cost table
    report = {"training_log": log, "spent": {"phase2": log["spent"]}}
    if context.logged_data is not None:
        budget = from_budget(LoggedTuningConfig, context)
        tuning = {
            **description,
            "logged_data": context.logged_data.fingerprint(),
            "tuning": asdict(budget),
        }
        logged = load_or_train(
            context,
            tuning,
            network,
            lambda _: _fine_tune(context, network, config, budget, rule, tuning),
        )
        report["logged_data_log"] = logged
        report["spent"]["logged_data"] = logged["spent"]
    return report
