"""KalmanNet: the EKF's recursion on the nominal model with a learned Kalman gain.

After Revach, Shlezinger, Ni, Lopez Escoriza, van Sloun and Eldar, "KalmanNet:
Neural network aided Kalman filtering for partially known dynamics", IEEE
Trans. Signal Processing 70 (2022), architecture 1. Each step::

    prior     x_{k|k-1} = RK4(x_{k-1|k-1}, u_{k-1})       (the nominal model, no Jacobian)
    features  F1 = y_k - y_{k-1}                          observation difference
              F2 = y_k - h(x_{k|k-1})                     innovation
              F3 = x_{k-1|k-1} - x_{k-2|k-2}              forward-evolution difference
              F4 = x_{k-1|k-1} - x_{k-1|k-2}              forward-update difference
    gain      K_k = FC(GRU(FC([F1, F2, F3, F4])))          (n_x, n_y)
    update    x_{k|k} = x_{k|k-1} + K_k F2                 (at the samples measured)

The GRU's state carries what a Kalman filter keeps in its covariances. The
filter starts at the centre of the x0 box (``x_{0|-1}``) with zero
differences. It is trained end to end through time (truncated
backpropagation, :mod:`kkl_bench.kkl.sequence`) on the same training
families, streams and budget keys as ``gru_observer``; on the ``mismatch``
track, with logged data, it is fine-tuned on them the same way.

Decisions (``docs/protocol.md`` section 6.2): the paper normalizes each
feature vector to unit length, which with one output leaves only the sign
of ``F1`` and ``F2``; here each feature is divided by a fixed scale from the
training data instead (the standard deviation of one-step changes of ``y``
for ``F1``, ``F2``, and of ``x`` for ``F3``, ``F4``). Estimates are clipped
to the training states' mean plus or minus 10 standard deviations, so a gain
that is still wrong early in training cannot overflow the nominal model.
With ``gain_init="ekf"`` (a decision of this project, protocol section 6.2) the
network's output is a correction added to the EKF's mean gain on training
trajectories (:func:`ekf_mean_gain`): the paper's initialisation starts from
the open-loop model, which on Lorenz-96 with 10 or more states trained into
a filter stuck at its clip bounds (RMSE 37); from the EKF's gain it trains.
It runs on one thread: its per-sample operations are too small for a second
one to pay (a GRU-cell step of 8 trajectories took 17 ms with two threads on
a loaded 2-core machine, 0.3 ms with one). Where the budget says
``compile_step`` (the standard profile, on the paper's systems), training runs
the step compiled by ``torch.compile`` (:meth:`KalmanNetFilter.compile_step`,
protocol section 6.5): the same arithmetic in fewer, fused operations.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace

import numpy as np
import torch
from kkl_bench.estimators.filters.ekf import ExtendedKalman
from kkl_bench.estimators.filters.kalman import box_prior
from torch import nn

from kkl_bench.estimator import Estimator, FitContext
from kkl_bench.kkl.config import from_budget
from kkl_bench.kkl.gain import simulate_families
from kkl_bench.kkl.networks import seeded
from kkl_bench.kkl.sequence import (
    RecurrentConfig,
    estimates,
    fit_sequence_model,
    model_description,
)
from kkl_bench.protocol.metrics import steady_state_start
from kkl_bench.protocol.simulate import rk4_step
from kkl_bench.protocol.system import System
from kkl_bench.registry import estimators, regimes
from kkl_bench.support.devices import compile_failure, resolve
from kkl_bench.support.executors import thread_limit
from kkl_bench.training import FORCED_TRAINING

KIND = "kalmannet"
VERSION = 1
"""Bump when a change to this module changes what a given configuration trains."""
CLIP_STDS = 10.0
"""Estimates are kept within the training states' mean +/- this many standard deviations."""


class KalmanNetFilter(nn.Module):
    """The filter as a sequence network (the interface of :mod:`kkl_bench.kkl.sequence`).

    ``forward(yu, state)``: ``yu: (batch, steps, n_y + 1)`` measurements and held
    inputs, then, if ``observed_channel``, the channel marking the samples measured
    (elsewhere ``y`` is the last measurement held, and the innovation is not applied);
    ``state`` None (start at ``t = 0``) or the tuple a previous call returned; returns
    ``x_hat: (batch, steps, n_x)`` and the final state.
    """

    def __init__(
        self,
        system: System,
        dt: float,
        prior_mean: torch.Tensor,
        hidden: int,
        observed_channel: bool,
        base_gain: torch.Tensor | None = None,
    ) -> None:
        super().__init__()
        self.system, self.dt = system, dt
        self.observed_channel = observed_channel
        n_x, n_y = system.n_x, system.n_y
        self.input = nn.Sequential(nn.Linear(2 * n_y + 2 * n_x, hidden), nn.ReLU())
        self.gru = nn.GRUCell(hidden, hidden)
        self.output = nn.Sequential(
            nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, n_x * n_y)
        )
        with torch.no_grad():  # start near the open-loop model: a small gain
            self.output[-1].weight.mul_(0.01)
            self.output[-1].bias.zero_()
        self.register_buffer("prior_mean", prior_mean.float())
        if base_gain is not None:  # the learned gain is a correction to it
            self.register_buffer("base_gain", base_gain.float())
        else:
            self.base_gain = None
        for name, size in (
            ("out_mean", n_x),
            ("out_scale", n_x),
            ("dy_scale", n_y),
            ("dx_scale", n_x),
        ):
            self.register_buffer(name, torch.ones(size))
        self.compiled_step = None

    def set_normalization(self, yu: torch.Tensor, x: torch.Tensor) -> None:
        """Scales from training data ``yu: (n, steps, n_y + 1)``, ``x: (n, steps, n_x)``."""
        n_y = self.system.n_y
        flat = x.reshape(-1, x.shape[-1])
        self.out_mean.copy_(flat.mean(0))
        self.out_scale.copy_(flat.std(0).clamp_min(1e-6))
        dy = yu[:, 1:, :n_y] - yu[:, :-1, :n_y]
        self.dy_scale.copy_(dy.reshape(-1, n_y).std(0).clamp_min(1e-6))
        dx = x[:, 1:] - x[:, :-1]
        self.dx_scale.copy_(dx.reshape(-1, x.shape[-1]).std(0).clamp_min(1e-6))

    def normalized(self, yu: torch.Tensor, state=None):
        x_hat, state = self.forward(yu, state)
        return (x_hat - self.out_mean) / self.out_scale, state

    def forward(self, yu: torch.Tensor, state=None):
        """Run the filter over ``yu``; ``state`` is ``(posterior, previous posterior,
        previous prior, previous y, previous u, GRU state)`` after the last sample of a
        previous call, or None to start at ``t = 0``. With gradients on and
        :meth:`compile_step` called, the samples after the first run compiled."""
        n_y = self.system.n_y
        batch, steps, _ = yu.shape
        low = self.out_mean - CLIP_STDS * self.out_scale
        high = self.out_mean + CLIP_STDS * self.out_scale
        step = self.step
        if self.compiled_step is not None and torch.is_grad_enabled():
            step = self.compiled_step
        estimates = []
        for k in range(steps):
            y, u = yu[:, k, :n_y], yu[:, k, n_y]
            observed = yu[:, k, n_y + 1 :] if self.observed_channel else None
            if state is None:  # t = 0: the prior is the box centre, every difference zero
                centre = self.prior_mean.expand(batch, -1)
                hidden = yu.new_zeros(batch, self.gru.hidden_size)
                posterior = prior = centre
                updated, hidden = self.correct(
                    prior, y, observed, centre, centre, centre, y, hidden, low, high
                )
            else:
                posterior, previous_posterior, previous_prior, previous_y, previous_u, hidden = (
                    state
                )
                updated, prior, hidden = step(
                    posterior, previous_u, y, observed, previous_posterior, previous_prior,
                    previous_y, hidden, low, high,
                )  # fmt: skip
            state = (updated, posterior, prior, y, u, hidden)
            estimates.append(updated)
        return torch.stack(estimates, dim=1), state

    def step(
        self, posterior, previous_u, y, observed, previous_posterior, previous_prior,
        previous_y, hidden, low, high,
    ):  # fmt: skip
        """One sample after the first: the nominal model's prior from ``posterior``
        ``(batch, n_x)`` and ``previous_u`` ``(batch,)``, then :meth:`correct`. Returns the
        posterior, the prior and the GRU state."""
        prior = rk4_step(self.system, posterior, previous_u, self.dt)
        updated, hidden = self.correct(
            prior, y, observed, posterior, previous_posterior, previous_prior, previous_y,
            hidden, low, high,
        )  # fmt: skip
        return updated, prior, hidden

    def correct(
        self, prior, y, observed, posterior, previous_posterior, previous_prior, previous_y,
        hidden, low, high,
    ):  # fmt: skip
        """The update of ``prior`` ``(batch, n_x)`` by the measurement ``y`` ``(batch, n_y)``
        (applied where ``observed``, ``(batch, 1)`` or None for every sample) through the
        learned gain, clamped to ``[low, high]``; ``posterior`` is the previous sample's
        update, the other ``previous_*`` are one sample older (the features F1-F4).
        Returns the update and the GRU state."""
        innovation = y - self.system.h(prior)
        if observed is not None:
            innovation = innovation * observed
        features = torch.cat(
            [
                (y - previous_y) / self.dy_scale,
                innovation / self.dy_scale,
                (posterior - previous_posterior) / self.dx_scale,
                (posterior - previous_prior) / self.dx_scale,
            ],
            dim=-1,
        )
        hidden = self.gru(self.input(features), hidden)
        gain = self.output(hidden).reshape(len(prior), self.system.n_x, self.system.n_y)
        if self.base_gain is not None:
            gain = gain + self.base_gain
        updated = prior + (gain @ innovation[..., None])[..., 0]
        return torch.clamp(updated, low, high), hidden

    def compile_step(self) -> None:
        """Train with :meth:`step` compiled by ``torch.compile`` (see :func:`compiles_step`):
        the same arithmetic, its elementwise operations fused, so float32 rounding differs
        from the eager step's. Estimates (gradients off) stay eager. Compiling forgets the
        code compiled for earlier networks (``torch.compiler.reset``): a process that fits
        several systems in turn would otherwise reach torch's recompile limit."""
        torch.compiler.reset()
        self.compiled_step = torch.compile(self.step, fullgraph=True, dynamic=False)


GAIN_INITS = ("zero", "ekf")

EKF_INIT_LR_SCALE = 0.1
"""With ``gain_init="ekf"`` the learning rate is the budget's ``rnn_lr`` times this: the
network corrects a filter that already tracks, and at the full rate (3e-3) the first 30
Adam steps threw Lorenz-96 n = 10 to its clip bounds (validation RMSE 0.30 -> 37.2);
at 3e-4 it fell to 0.038 in 300 steps (protocol section 6.2)."""

EKF_GAIN_TRAJECTORIES = 4
"""Unforced and as many forced training-stream trajectories the EKF's mean gain is taken on."""


def ekf_mean_gain(context: FitContext) -> np.ndarray:
    """The EKF's Kalman gain ``(n_x, n_y)`` averaged over the measured samples of the
    scored window of :data:`EKF_GAIN_TRAJECTORIES` unforced and as many forced
    trajectories of a training stream (``kalmannet/ekf-gain``)."""
    families = {"unforced": regimes.get("zero")(), "forced": FORCED_TRAINING}
    _, y, u = simulate_families(context, families, EKF_GAIN_TRAJECTORIES, "kalmannet/ekf-gain")
    # the plain EKF on every task (the gain that KalmanNet's training has started from)
    ekf = ExtendedKalman(inflation=1.0, robust="none", quantizer="in-model").fit(context)
    start = steady_state_start(y.shape[1])
    gains = []
    for b in range(len(y)):
        kalman_filter = ekf.make_filter(ekf.settings_, context.dt)
        for k in range(y.shape[1]):
            ekf.step(kalman_filter, None if k == 0 else float(u[b, k - 1, 0]), y[b, k])
            if k >= start and np.isfinite(y[b, k]).all():
                gains.append(kalman_filter.K)
    return np.mean(gains, axis=0)


@estimators.register("kalmannet")
class KalmanNet(Estimator):
    """KalmanNet on the nominal model (see the module doc). Sizes and training come from
    the profile's budget (``rnn_*`` keys, as ``gru_observer``).

    Parameters
    ----------
    gain_init: ``"zero"`` (the paper's): the gain starts near zero, the open-loop model;
        ``"ekf"``: the network learns a correction to the EKF's mean gain
        (:func:`ekf_mean_gain`), so training starts from a filter that tracks, at a
        tenth of the learning rate (:data:`EKF_INIT_LR_SCALE`).
    """

    name = "kalmannet"
    family = "learned"
    uses_logged_data = True
    supported_measurements = frozenset({"sensor", "sampling", "noise"})
    """Trained on the task's measurement model (``FitContext.training``); under a sparse
    sampling the update is applied at the measured samples only."""

    def __init__(self, gain_init: str = "zero") -> None:
        self.gain_init = gain_init
        if gain_init not in GAIN_INITS:
            raise ValueError(f"kalmannet: gain_init={gain_init!r}; valid: {', '.join(GAIN_INITS)}")

    def fit(self, context: FitContext):
        config = from_budget(RecurrentConfig, context)
        system = context.system
        base_gain = None
        if self.gain_init == "ekf":
            base_gain = ekf_mean_gain(context)
            config = replace(config, rnn_lr=EKF_INIT_LR_SCALE * config.rnn_lr)
        with seeded(context.seed):
            network = KalmanNetFilter(
                system,
                context.dt,
                torch.as_tensor(box_prior(context)[0]),
                config.rnn_hidden,
                observed_channel="sampling" in context.measurement.features,
                base_gain=None if base_gain is None else torch.as_tensor(base_gain),
            )
        compiled = compiles_step(context)
        if compiled:
            network.compile_step()
        description = model_description(
            KIND,
            VERSION,
            system,
            context.seed,
            **({"gain_init": self.gain_init} if self.gain_init != "zero" else {}),
            **({"compiled_step": True} if compiled else {}),
        )
        with thread_limit(1):
            self.report_ = fit_sequence_model(context, network, config, description)
        self.network_ = network
        return super().fit(context)

    def estimate(self, t, y, u):
        self.check_fitted()
        with thread_limit(1):
            return estimates(self.network_, y, u)

    def fit_report(self):
        return {**self.report_, "gain_init": self.gain_init}


@dataclass(frozen=True)
class StepCompilation:
    """Budget key ``compile_step``: train with the filter's step compiled
    (:meth:`KalmanNetFilter.compile_step`). Compiling takes about half a minute, which a
    standard fit repays many times over and a quick one does not."""

    compile_step: bool = False


def compiles_step(context: FitContext) -> bool:
    """Whether a fit in ``context`` trains with the step compiled: its budget asks for it,
    it trains on the CPU, and torch can compile there (:func:`~kkl_bench.support.devices.compile_failure`;
    if not, a warning says why and training runs eagerly)."""
    if not from_budget(StepCompilation, context).compile_step or resolve(context.device) != "cpu":
        return False
    failure = compile_failure()
    if failure is not None:
        warnings.warn(
            f"kalmannet: the budget asks for a compiled step, but torch.compile fails on this "
            f"machine ({failure}); training eagerly (slower; the model differs by float32 "
            "rounding from a compiled training's)",
            stacklevel=2,
        )
    return failure is None
