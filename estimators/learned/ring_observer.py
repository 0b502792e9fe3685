"""Local observer for systems on a ring (Lorenz-96): the model's prediction, corrected by a
gain that one small recurrent network, shared by every site, learns from its neighbourhood.

Each step, for every site ``s`` (``System.ring``)::

    prior       x_{k|k-1} = RK4(x_{k-1|k-1}, u_{k-1})        (the model, O(n))
    innovation  e_k = y_k - h(x_{k|k-1}), placed at the measured sites (0 elsewhere)
    features    of the sites within ``radius`` of s: innovation, measured mark, prior
    gain        K_s = Linear(GRUCell(features, hidden_s))   (per_site x (2 radius + 1))
    update      x_{k|k}[s] = x_{k|k-1}[s] + K_s e_k[neighbourhood of s]

like KalmanNet's update, but local: the same weights at every site, so the
network has the same parameters at every ring size, commutes with the
rotations of the ring that keep its measurement pattern (with the input
off), costs O(n) per sample, and can be trained at one size and applied at
another (``train_sites``). The gain starts as nudging: ``NUDGING`` on a
site's own innovation and 0 elsewhere, so that the untrained filter already
follows the measured sites instead of the chaotic model's open loop. The
ring is the system's declaration (:class:`~kkl_bench.protocol.system.Ring`);
on a system that declares none the estimator's cells are ``unsupported``.

Scalings are pooled over sites (one for every innovation, one for every
state), so they do not depend on the size either. Training is
``gru_observer``'s (:mod:`kkl_bench.kkl.sequence`: truncated backpropagation
through time on the training families, cached and checkpointed) with one
change: a step draws ``max(1, ring_site_batch // sites)`` trajectories, so
every step sees about the same number of site histories at every size and
the budget does not grow with the ring. The filter starts at the x0 box's
centre and clips its estimates to the training states' mean plus or minus
10 deviations, as ``kalmannet`` does.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass

import torch
from torch import nn

from kkl_bench.estimator import Estimator, FitContext
from kkl_bench.kkl.config import from_budget
from kkl_bench.kkl.networks import seeded
from kkl_bench.kkl.sequence import (
    RecurrentConfig,
    estimates,
    fit_sequence_model,
    model_description,
)
from kkl_bench.measurement import MeasurementModel
from kkl_bench.protocol.simulate import rk4_step
from kkl_bench.protocol.system import System
from kkl_bench.registry import estimators
from kkl_bench.support.executors import thread_limit

KIND = "ring-observer"
VERSION = 2
"""Bump when a change to this module changes what a given configuration trains."""
NUDGING = 0.5
"""The untrained gain on a site's own innovation."""
CLIP_STDS = 10.0
"""Estimates are kept within the training states' mean +/- this many standard deviations."""


@dataclass(frozen=True)
class RingConfig:
    """The ring observer's own budget key (read with :func:`from_budget`)."""

    ring_site_batch: int = 320
    """Site histories per optimizer step: ``max(1, ring_site_batch // sites)`` trajectories."""


class RingLayout:
    """A ring system as the network reads it: the system, its box centre and the index
    tensors of its sites. ``system.ring`` must be set; ``radius`` sites each side."""

    def __init__(self, system: System, radius: int) -> None:
        ring = system.ring
        self.system, self.radius = system, radius
        self.sites = ring.sites
        self.per_site = system.n_x // ring.sites
        self.output_sites = torch.as_tensor(ring.output_sites)
        self.measured = torch.zeros(ring.sites)
        self.measured[self.output_sites] = 1.0
        self.centre = torch.as_tensor((system.x0_low + system.x0_high) / 2, dtype=torch.float32)
        offsets = torch.arange(-radius, radius + 1)
        self.neighbours = (torch.arange(ring.sites)[:, None] + offsets) % ring.sites

    def around(self, per_site: torch.Tensor) -> torch.Tensor:
        """``(batch, sites, c)`` -> ``(batch, sites, 2 radius + 1, c)``: each site's neighbourhood."""
        return per_site[:, self.neighbours]


class LocalRingFilter(nn.Module):
    """The filter as a sequence network (the interface of :mod:`kkl_bench.kkl.sequence`).

    ``forward(yu, state)``: ``yu: (batch, steps, n_y + 1)`` measurements and inputs
    (then the channel marking measured samples if ``observed_channel``); ``state``
    None (start at ``t = 0``) or ``(posterior (batch, n_x), previous u (batch,),
    hidden (batch * sites, hidden))``; returns ``x_hat: (batch, steps, n_x)`` and the
    final state. :meth:`on` gives the same network for another ring.
    """

    def __init__(
        self, layout: RingLayout, dt: float, radius: int, hidden: int, observed_channel: bool
    ) -> None:
        super().__init__()
        self.layout, self.dt, self.observed_channel = layout, dt, observed_channel
        width = 2 * radius + 1
        channels = 2 + layout.per_site  # innovation, measured mark, prior per state
        self.cell = nn.GRUCell(channels * width, hidden)
        self.gain = nn.Linear(hidden, layout.per_site * width)
        with torch.no_grad():  # start as nudging: NUDGING on the site's own innovation
            self.gain.weight.mul_(0.01)
            self.gain.bias.zero_()
            own = torch.zeros(layout.per_site, width)
            own[:, radius] = NUDGING
            self.gain.bias.copy_(own.reshape(-1))
        for name in ("e_scale", "out_mean", "out_scale"):
            self.register_buffer(name, torch.ones(1))

    def on(self, system: System) -> LocalRingFilter:
        """This network (the same parameters and scalings) on ``system``'s ring."""
        moved = copy.copy(self)  # shares the parameter and buffer dicts; only the layout differs
        moved.layout = RingLayout(system, self.layout.radius)
        return moved

    def set_normalization(self, yu: torch.Tensor, x: torch.Tensor) -> None:
        """Pooled scalings from training data ``yu: (n, steps, n_y + 1 [+ 1])``,
        ``x: (n, steps, n_x)``: the states' mean and deviation, and the deviation of the
        measurements' one-step changes (the innovations' scale)."""
        n_y = len(self.layout.output_sites)
        changes = yu[:, 1:, :n_y] - yu[:, :-1, :n_y]
        self.e_scale.fill_(max(changes.std().item(), 1e-6))
        self.out_mean.fill_(x.mean().item())
        self.out_scale.fill_(max(x.std().item(), 1e-6))

    def normalized(self, yu: torch.Tensor, state=None):
        x_hat, state = self.forward(yu, state)
        return (x_hat - self.out_mean) / self.out_scale, state

    def forward(self, yu: torch.Tensor, state=None):
        layout = self.layout
        system, n_y, sites = layout.system, len(layout.output_sites), layout.sites
        batch, steps, _ = yu.shape
        low = self.out_mean - CLIP_STDS * self.out_scale
        high = self.out_mean + CLIP_STDS * self.out_scale
        if state is None:
            posterior = None
            hidden = yu.new_zeros(batch * sites, self.cell.hidden_size)
        else:
            posterior, previous_u, hidden = state
        measured = layout.measured.expand(batch, -1)
        posteriors = []
        for k in range(steps):
            y, u = yu[:, k, :n_y], yu[:, k, n_y]
            if posterior is None:  # t = 0: the prior is the box centre
                prior = layout.centre.expand(batch, -1)
            else:
                prior = rk4_step(system, posterior, previous_u, self.dt)
            mark = measured
            innovation = yu.new_zeros(batch, sites)
            innovation[:, layout.output_sites] = (y - system.h(prior)) / self.e_scale
            if self.observed_channel:
                mark = mark * yu[:, k, -1:]
                innovation = innovation * mark
            standard_prior = ((prior - self.out_mean) / self.out_scale).reshape(batch, sites, -1)
            features = torch.cat([innovation[..., None], mark[..., None], standard_prior], -1)
            around = layout.around(features).reshape(batch * sites, -1)
            hidden = self.cell(around, hidden)
            gain = self.gain(hidden).reshape(batch, sites, layout.per_site, -1)
            local = layout.around(innovation[..., None])[..., 0]  # (batch, sites, width)
            correction = (gain @ local[..., None])[..., 0] * self.e_scale
            posterior = torch.clamp(prior + correction.reshape(batch, -1), low, high)
            previous_u = u
            posteriors.append(posterior)
        return torch.stack(posteriors, dim=1), (posterior, previous_u, hidden)


@estimators.register("ring_observer")
class RingObserver(Estimator):
    """The model's prediction corrected by a local gain shared by the sites of a ring (see
    the module doc).

    Parameters
    ----------
    radius: sites read on each side of a site.
    train_sites: train on the same system with this many sites (``System.with_sites``)
        and apply at the size asked for; None (default): train at that size.
    """

    name = "ring_observer"
    family = "learned"
    supported_measurements = frozenset({"sensor", "sampling", "noise"})
    """Trained on the task's measurement model; under a sparse sampling the innovation is
    applied at the samples measured only."""

    def __init__(self, radius: int = 3, train_sites: int | None = None) -> None:
        self.radius = radius
        self.train_sites = train_sites
        if not (isinstance(radius, int) and radius >= 1):
            raise ValueError(f"ring_observer: radius={radius!r} must be a positive integer")
        if train_sites is not None and not (isinstance(train_sites, int) and train_sites >= 4):
            raise ValueError(
                f"ring_observer: train_sites={train_sites!r} must be an integer of at least 4, "
                "or None"
            )

    def unsupported_reason(self, system: System, measurement: MeasurementModel) -> str | None:
        if system.ring is None:
            return (
                f"needs a system on a ring (System.ring: its sites and which are measured); "
                f"{system.name} declares none"
            )
        return super().unsupported_reason(system, measurement)

    def fit(self, context: FitContext):
        training = self._training_context(context)
        system = training.system
        config = from_budget(RecurrentConfig, training)
        ring_config = from_budget(RingConfig, training)
        config = dataclasses.replace(
            config, rnn_batch=max(1, ring_config.ring_site_batch // system.ring.sites)
        )
        with seeded(training.seed):
            network = LocalRingFilter(
                RingLayout(system, self.radius),
                training.dt,
                self.radius,
                config.rnn_hidden,
                observed_channel="sampling" in training.measurement.features,
            )
        description = model_description(
            KIND,
            VERSION,
            system,
            training.seed,
            radius=self.radius,
            ring=dataclasses.asdict(ring_config),
        )
        with thread_limit(1):
            self.report_ = fit_sequence_model(training, network, config, description)
        self.report_["trained_on"] = system.name
        self.network_ = network.on(context.system)
        return super().fit(context)

    def _training_context(self, context: FitContext) -> FitContext:
        """``context``, or the same system resized to ``train_sites`` sites."""
        if self.train_sites is None or self.train_sites == context.system.ring.sites:
            return context
        resized = context.measurement.system(context.system.with_sites(self.train_sites))
        return dataclasses.replace(
            context, system=resized, training=context.training.with_system(resized)
        )

    def estimate(self, t, y, u):
        self.check_fitted()
        with thread_limit(1):
            return estimates(self.network_, y, u)

    def fit_report(self):
        return self.report_
