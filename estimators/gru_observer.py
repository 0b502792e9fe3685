"""Recurrent observer: a GRU (or LSTM) mapping the history of ``(y, u)`` to ``x``.

The baseline a machine-learning user tries first, with no model structure:
inputs ``(y_k, u_k)`` standardized, a stacked recurrent network whose hidden
state is carried over the whole trajectory from zero at ``t = 0``, and a
linear read-out of ``x_hat_k`` in standardized state units (so the loss
weighs the states as the benchmark's RMSE does).

Training data are trajectories of the training streams only: half unforced,
half forced by :data:`~kkl_bench.kkl.inputs.FORCED_TRAINING` (the KKL plugins'
training families). Training is truncated backpropagation through time in
sweeps: ``rnn_batch`` trajectories are walked from ``t = 0`` in consecutive
windows of ``rnn_window`` samples, one Adam step per window, the hidden state
carried from window to window as it is at test time. The model is cached and
its training checkpointed like the KKL models
(:func:`kkl_bench.kkl.phase2.load_or_train`,
:func:`kkl_bench.kkl.optimize.resumable`); the fit report records the steps,
samples and the RMSE on validation trajectories of a separate training
stream.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import nn

from kkl_bench.estimator import Estimator, FitContext
from kkl_bench.kkl.config import from_budget
from kkl_bench.kkl.gain import simulate_families
from kkl_bench.kkl.inputs import FORCED_TRAINING
from kkl_bench.kkl.networks import seeded
from kkl_bench.kkl.optimize import minimize, resumable
from kkl_bench.kkl.phase2 import load_or_train
from kkl_bench.protocol import PROTOCOL_ID
from kkl_bench.protocol.metrics import rmse
from kkl_bench.registry import estimators, regimes

CELLS = {"gru": nn.GRU, "lstm": nn.LSTM}
KIND = "recurrent-observer"
VERSION = 2
"""Bump when a change to this module changes what a given configuration trains."""


@dataclass(frozen=True)
class RecurrentConfig:
    """The training budget (read with :func:`kkl_bench.kkl.config.from_budget`)."""

    rnn_hidden: int = 64
    rnn_layers: int = 2
    rnn_trajectories: int = 128
    """Training trajectories of each kind (unforced, forced)."""
    rnn_validation: int = 16
    """Validation trajectories of each kind (a separate training stream)."""
    rnn_steps: int = 4000
    rnn_batch: int = 32
    rnn_window: int = 200
    """Samples one step backpropagates through."""
    rnn_lr: float = 3e-3


class RecurrentObserver(nn.Module):
    """Standardize ``(y, u)``, run the recurrent cell, read out standardized ``x``.

    ``forward(yu, state)``: ``yu: (batch, steps, n_y + 1)`` in physical units,
    ``state`` the cell's hidden state or None (zeros); returns ``x_hat:
    (batch, steps, n_x)`` in physical units and the final hidden state.
    """

    def __init__(self, n_in: int, n_x: int, hidden: int, layers: int, cell: str) -> None:
        super().__init__()
        self.cell = CELLS[cell](n_in, hidden, num_layers=layers, batch_first=True)
        self.readout = nn.Linear(hidden, n_x)
        for name, size in (("in", n_in), ("out", n_x)):
            self.register_buffer(f"{name}_mean", torch.zeros(size))
            self.register_buffer(f"{name}_scale", torch.ones(size))

    def set_normalization(self, yu: torch.Tensor, x: torch.Tensor) -> None:
        """Per-channel mean and standard deviation from ``yu: (..., n_in)`` and ``x: (..., n_x)``."""
        for name, samples in (("in", yu), ("out", x)):
            flat = samples.reshape(-1, samples.shape[-1])
            getattr(self, f"{name}_mean").copy_(flat.mean(0))
            getattr(self, f"{name}_scale").copy_(flat.std(0).clamp_min(1e-6))

    def normalized(self, yu: torch.Tensor, state=None):
        """Standardized estimates ``(batch, steps, n_x)`` and the final hidden state."""
        hidden, state = self.cell((yu - self.in_mean) / self.in_scale, state)
        return self.readout(hidden), state

    def forward(self, yu: torch.Tensor, state=None):
        out, state = self.normalized(yu, state)
        return self.out_mean + out * self.out_scale, state


def _inputs(y: np.ndarray, u: np.ndarray) -> torch.Tensor:
    """``(batch, steps, n_y + 1)`` float32 network inputs from ``y`` and ``u``."""
    return torch.as_tensor(np.concatenate([y, u], axis=-1), dtype=torch.float32)


def _train(
    network: RecurrentObserver,
    yu: torch.Tensor,
    x: torch.Tensor,
    config: RecurrentConfig,
    seed: int,
    label: str,
) -> list[float]:
    """Truncated BPTT over ``yu: (n, steps, n_in)`` against ``x: (n, steps, n_x)``.

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
    )


def _fit(context: FitContext, network: RecurrentObserver, config, description) -> dict:
    """Train ``network`` on the training families; the training log with its validation RMSE."""
    families = {"unforced": regimes.get("zero")(), "forced": FORCED_TRAINING}
    x, y, u = simulate_families(context, families, config.rnn_trajectories, "rnn/train")
    yu, x = _inputs(y, u), torch.as_tensor(x, dtype=torch.float32)
    network.set_normalization(yu, x)
    with resumable(context.cache_dir, description, []):
        losses = _train(network, yu, x, config, context.seed, f"{context.system.name}: {KIND}")
    x_val, y_val, u_val = simulate_families(
        context, families, config.rnn_validation, "rnn/validation"
    )
    with torch.no_grad():
        x_hat, _ = network(_inputs(y_val, u_val))
    return {
        "final_loss": float(np.mean(losses[-100:])),
        "validation_rmse": float(rmse(x_val, x_hat.double().numpy()).mean()),
    }


@estimators.register("gru_observer")
class GRUObserver(Estimator):
    """A recurrent network from ``(y, u)`` histories to ``x`` (no model structure).

    Parameters
    ----------
    cell: ``"gru"`` or ``"lstm"``.
    """

    name = "gru_observer"

    def __init__(self, cell: str = "gru") -> None:
        self.cell = cell

    def fit(self, context: FitContext):
        if self.cell not in CELLS:
            raise ValueError(f"unknown cell {self.cell!r}; valid cells: {', '.join(CELLS)}")
        config = from_budget(RecurrentConfig, context)
        system = context.system
        with seeded(context.seed):
            network = RecurrentObserver(
                system.n_y + 1, system.n_x, config.rnn_hidden, config.rnn_layers, self.cell
            )
        description = {
            "kind": KIND,
            "version": VERSION,
            "protocol": PROTOCOL_ID,
            "system": system.name,
            "seed": context.seed,
            "cell": self.cell,
            "config": asdict(config),
        }
        self.log_ = load_or_train(
            context, description, network, lambda: _fit(context, network, config, description)
        )
        self.network_ = network
        return super().fit(context)

    def estimate(self, t, y, u):
        self.check_fitted()
        with torch.inference_mode():
            x_hat, _ = self.network_(_inputs(y, u))
        return x_hat.double().numpy()

    def fit_report(self):
        # no Phase 1: the network's own training is its second phase in the cost table
        return {"training_log": self.log_, "spent": {"phase2": self.log_["spent"]}}
