"""Local observer for systems on a ring (Lorenz-96): one recurrent network shared by every site.

Each site ``s`` reads, at every sample, the features of the sites within
``radius`` of it (``s - radius, ..., s + radius`` modulo the ring): the site's
measurement (0 at a site without an output), a 0/1 channel marking the
measured sites (and, under a sparse sampling, the samples measured), and the
input as it enters the site's states (``g_s u``). A GRU shared by all sites
maps the history of its neighbourhood's features to the site's states; the
sites run as one batch. The network therefore has the same parameters at
every ring size, commutes with the rotations of the ring that keep its
measurement pattern (and with the input off), costs O(n) per sample, and can
be trained at one size and applied at another (``train_sites``). The ring is
the system's declaration (:class:`~kkl_bench.protocol.system.Ring`); on a
system that declares none the estimator's cells are ``unsupported``.

Scalings are pooled over sites (one mean and deviation for every
measurement, one for every state), so they do not depend on the size either.
Training is ``gru_observer``'s (:mod:`kkl_bench.kkl.sequence`: truncated
backpropagation through time on the training families, cached and
checkpointed) with one change: a step draws ``max(1, ring_site_batch //
sites)`` trajectories, so that every step sees about the same number of
site histories at every size and the budget (steps, samples of each site)
does not grow with the ring.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from kkl_bench.estimator import Estimator, FitContext
from kkl_bench.kkl.config import from_budget
from kkl_bench.kkl.networks import seeded
from kkl_bench.kkl.sequence import RecurrentConfig, fit_sequence_model, inputs
from kkl_bench.measurement import MeasurementModel
from kkl_bench.protocol import PROTOCOL_ID
from kkl_bench.protocol.system import System
from kkl_bench.registry import estimators

KIND = "ring-observer"
VERSION = 1
"""Bump when a change to this module changes what a given configuration trains."""
ESTIMATE_CHUNK = 200
"""Samples per call of the recurrent network when estimating (bounds the memory of the
neighbourhood features at large rings; the hidden state is carried across chunks)."""


@dataclass(frozen=True)
class RingConfig:
    """The ring observer's own budget key (read with :func:`from_budget`)."""

    ring_site_batch: int = 320
    """Site histories per optimizer step: ``max(1, ring_site_batch // sites)`` trajectories."""


class RingLayout:
    """Where a ring system's outputs and input sit: the index tensors the network gathers with.

    ``system.ring`` must be set; ``per_site`` states per site, ``radius`` sites each side.
    """

    def __init__(self, system: System, radius: int) -> None:
        ring = system.ring
        self.sites = ring.sites
        self.per_site = system.n_x // ring.sites
        self.n_y = system.n_y
        self.output_sites = torch.as_tensor(ring.output_sites)
        self.measured = torch.zeros(ring.sites)
        self.measured[self.output_sites] = 1.0
        self.g = torch.as_tensor(
            np.reshape(system.g, (ring.sites, self.per_site)), dtype=torch.float32
        )
        offsets = torch.arange(-radius, radius + 1)
        self.neighbours = (torch.arange(ring.sites)[:, None] + offsets) % ring.sites


class LocalRingNetwork(nn.Module):
    """The shared per-site GRU with pooled scalings (the :mod:`kkl_bench.kkl.sequence` interface).

    ``forward(yu, state)``: ``yu: (batch, steps, n_y + 1)`` (then the channel marking
    measured samples if ``observed_channel``), ``state`` the GRU's ``(layers, batch *
    sites, hidden)`` or None; returns ``x_hat: (batch, steps, n_x)`` and the final state.
    :meth:`on` gives the same network for another ring size.
    """

    def __init__(
        self,
        layout: RingLayout,
        radius: int,
        hidden: int,
        layers: int,
        observed_channel: bool,
    ) -> None:
        super().__init__()
        self.layout, self.observed_channel = layout, observed_channel
        channels = 2 + layout.per_site  # measurement, measured mark, input per state
        self.cell = nn.GRU(channels * (2 * radius + 1), hidden, layers, batch_first=True)
        self.readout = nn.Linear(hidden, layout.per_site)
        for name in ("y_mean", "y_scale", "u_scale", "out_mean", "out_scale"):
            self.register_buffer(name, torch.ones(1))

    def on(self, system: System) -> LocalRingNetwork:
        """This network (the same parameters and scalings) reading ``system``'s ring."""
        moved = copy.copy(self)  # shares the parameter and buffer dicts; only the layout differs
        moved.layout = RingLayout(system, (self.layout.neighbours.shape[1] - 1) // 2)
        return moved

    def set_normalization(self, yu: torch.Tensor, x: torch.Tensor) -> None:
        """Pooled scalings from training data ``yu: (n, steps, n_y + 1 [+ 1])``, ``x: (n, steps, n_x)``."""
        n_y = self.layout.n_y
        self.y_mean.fill_(yu[..., :n_y].mean().item())
        self.y_scale.fill_(max(yu[..., :n_y].std().item(), 1e-6))
        self.u_scale.fill_(max(yu[..., n_y].std().item(), 1e-6))
        self.out_mean.fill_(x.mean().item())
        self.out_scale.fill_(max(x.std().item(), 1e-6))

    def features(self, yu: torch.Tensor) -> torch.Tensor:
        """``(batch * sites, steps, (2 radius + 1) channels)``: each site's neighbourhood."""
        layout = self.layout
        batch, steps, _ = yu.shape
        y = (yu[..., : layout.n_y] - self.y_mean) / self.y_scale
        value = yu.new_zeros(batch, steps, layout.sites)
        value[..., layout.output_sites] = y
        mark = layout.measured.expand(batch, steps, -1)
        if self.observed_channel:
            mark = mark * yu[..., -1:]
            value = value * mark
        forcing = (yu[..., layout.n_y, None, None] / self.u_scale) * layout.g
        per_site = torch.cat([value[..., None], mark[..., None], forcing], dim=-1)
        around = per_site[:, :, layout.neighbours]  # (batch, steps, sites, 2 r + 1, channels)
        rows = around.reshape(batch, steps, layout.sites, -1).transpose(1, 2)
        return rows.reshape(batch * layout.sites, steps, -1)

    def normalized(self, yu: torch.Tensor, state=None):
        batch, steps, _ = yu.shape
        hidden, state = self.cell(self.features(yu), state)
        out = self.readout(hidden)  # (batch * sites, steps, per_site)
        out = out.reshape(batch, self.layout.sites, steps, -1).transpose(1, 2)
        return out.reshape(batch, steps, -1), state

    def forward(self, yu: torch.Tensor, state=None):
        out, state = self.normalized(yu, state)
        return self.out_mean + out * self.out_scale, state


@estimators.register("ring_observer")
class RingObserver(Estimator):
    """A recurrent network shared by the sites of a ring (see the module doc).

    Parameters
    ----------
    radius: sites read on each side of a site.
    train_sites: train on the same system with this many sites (``System.with_sites``)
        and apply at the size asked for; None (default): train at that size.
    """

    name = "ring_observer"
    supported_measurements = frozenset({"sensor", "sampling", "noise"})
    """Trained on the task's measurement model; under a sparse sampling a site reads its
    last measurement held and the mark of the samples measured."""

    def __init__(self, radius: int = 4, train_sites: int | None = None) -> None:
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
        sparse = "sampling" in training.measurement.features
        with seeded(training.seed):
            network = LocalRingNetwork(
                RingLayout(system, self.radius),
                self.radius,
                config.rnn_hidden,
                config.rnn_layers,
                observed_channel=sparse,
            )
        description = {
            "kind": KIND,
            "version": VERSION,
            "protocol": PROTOCOL_ID,
            "system": system.name,
            "system_params": system.params(),
            "seed": training.seed,
            "radius": self.radius,
            "ring": dataclasses.asdict(ring_config),
        }
        self.report_ = {**fit_sequence_model(training, network, config, description)}
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
        yu = inputs(y, u, self.network_.observed_channel)
        state, parts = None, []
        with torch.inference_mode():
            for start in range(0, yu.shape[1], ESTIMATE_CHUNK):
                x_hat, state = self.network_(yu[:, start : start + ESTIMATE_CHUNK], state)
                parts.append(x_hat)
        return torch.cat(parts, dim=1).double().numpy()

    def fit_report(self):
        return self.report_
