"""Recurrent observer: a GRU (or LSTM) mapping the history of ``(y, u)`` to ``x``.

The baseline a machine-learning user tries first, with no model structure:
inputs ``(y_k, u_k)`` standardized, a stacked recurrent network whose hidden
state is carried over the whole trajectory from zero at ``t = 0``, and a
linear read-out of ``x_hat_k`` in standardized state units (so the loss
weighs the states as the benchmark's RMSE does).

Training data are trajectories of the training streams only: half unforced,
half forced by :data:`~kkl_bench.training.FORCED_TRAINING` (the KKL plugins'
training families). Training is truncated backpropagation through time in
sweeps: ``rnn_batch`` trajectories are walked from ``t = 0`` in consecutive
windows of ``rnn_window`` samples, one Adam step per window, the hidden state
carried from window to window as it is at test time, until the plateau rule
(protocol 6.5) stops it or ``rnn_steps`` is reached; the state with the lowest
validation error is kept. The model is cached and its training checkpointed
like the KKL models (:func:`kkl_bench.kkl.phase2.load_or_train`,
:func:`kkl_bench.kkl.optimize.resumable`); the fit report records the steps,
samples and the RMSE on validation trajectories of a separate training
stream.

With logged data of a true plant (the ``mismatch`` track), the nominally
trained network is fine-tuned on four fifths of the logged trajectories (the
same sweeps and rule, at most ``rnn_logged_steps`` Adam steps) and kept only
if its RMSE on the held-out fifth improves; the fit report records both RMSEs.
"""

from __future__ import annotations

import torch
from torch import nn

from kkl_bench.estimator import Estimator, FitContext
from kkl_bench.kkl.config import from_budget
from kkl_bench.kkl.networks import seeded
from kkl_bench.kkl.sequence import RecurrentConfig, estimates, fit_sequence_model
from kkl_bench.protocol import PROTOCOL_ID
from kkl_bench.registry import estimators

CELLS = {"gru": nn.GRU, "lstm": nn.LSTM}
KIND = "recurrent-observer"
VERSION = 2
"""Bump when a change to this module changes what a given configuration trains."""


class RecurrentObserver(nn.Module):
    """Standardize ``(y, u)``, run the recurrent cell, read out standardized ``x``.

    ``forward(yu, state)``: ``yu: (batch, steps, n_in)`` in physical units (``n_y + 1``
    channels, and the channel marking measured samples if ``observed_channel``),
    ``state`` the cell's hidden state or None (zeros); returns ``x_hat:
    (batch, steps, n_x)`` in physical units and the final hidden state.
    """

    def __init__(
        self, n_in: int, n_x: int, hidden: int, layers: int, cell: str, observed_channel: bool
    ) -> None:
        super().__init__()
        self.observed_channel = observed_channel
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


@estimators.register("gru_observer")
class GRUObserver(Estimator):
    """A recurrent network from ``(y, u)`` histories to ``x`` (no model structure).

    Parameters
    ----------
    cell: ``"gru"`` or ``"lstm"``.
    """

    name = "gru_observer"
    family = "learned"
    uses_logged_data = True
    supported_measurements = frozenset({"sensor", "sampling", "noise"})
    """Trained on the task's measurement model (``FitContext.training``); under a sparse
    sampling it reads the last measurement held and a channel marking the measured samples."""

    def __init__(self, cell: str = "gru") -> None:
        self.cell = cell

    def fit(self, context: FitContext):
        if self.cell not in CELLS:
            raise ValueError(f"unknown cell {self.cell!r}; valid cells: {', '.join(CELLS)}")
        config = from_budget(RecurrentConfig, context)
        system = context.system
        sparse = "sampling" in context.measurement.features
        with seeded(context.seed):
            network = RecurrentObserver(
                system.n_y + 1 + sparse,
                system.n_x,
                config.rnn_hidden,
                config.rnn_layers,
                self.cell,
                observed_channel=sparse,
            )
        description = {
            "kind": KIND,
            "version": VERSION,
            "protocol": PROTOCOL_ID,
            "system": system.name,
            "seed": context.seed,
            "cell": self.cell,
        }
        self.report_ = fit_sequence_model(context, network, config, description)
        self.network_ = network
        return super().fit(context)

    def estimate(self, t, y, u):
        self.check_fitted()
        return estimates(self.network_, y, u)

    def fit_report(self):
        return self.report_
