"""What the input-aware KKL plugins share in Phase 2: forced data, windows, caching.

Phase-2 data are forced trajectories (:data:`~kkl_bench.training.FORCED_TRAINING`
inputs, training streams only) run through the Phase-1 latent observer,
which ignores the input: ``z_k`` is what the observer holds at test time.
Samples are drawn from the protocol's scored window.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import torch
from torch import nn

from kkl_bench.estimator import FitContext
from kkl_bench.kkl.autonomous import AutonomousModel, fit_phase1
from kkl_bench.kkl.cache import CheckpointCache
from kkl_bench.kkl.config import from_budget
from kkl_bench.kkl.data import ObserverData, observer_data, validation_count
from kkl_bench.kkl.networks import seeded
from kkl_bench.kkl.optimize import counting, resumable
from kkl_bench.kkl.plateau import PlateauRule
from kkl_bench.kkl.windows import sliding_windows
from kkl_bench.protocol.metrics import steady_state_start
from kkl_bench.support.devices import draw_integers, training_on
from kkl_bench.training import FORCED_TRAINING


@dataclass(frozen=True)
class Phase2Config:
    """Budget of a Phase-2 training (read with :func:`kkl_bench.kkl.config.from_budget`)."""

    window: int = 100
    lstm_hidden: int = 64
    phase2_trajectories: int = 32
    phase2_steps: int = 1000
    phase2_batch: int = 256
    collocation_points: int = 8


@dataclass
class ForcedSamples:
    """Forced training data indexed by (trajectory, step) on the scored window.

    Attributes
    ----------
    data: the trajectories and observer states.
    windows: ``(n, steps, window + 1)`` input windows.
    """

    data: ObserverData
    windows: torch.Tensor
    _tensors: dict[str, torch.Tensor] = field(default_factory=dict, repr=False)

    @classmethod
    def simulate(
        cls, context: FitContext, model: AutonomousModel, config: Phase2Config
    ) -> ForcedSamples:
        """The training samples: ``phase2_trajectories`` forced trajectories."""
        return cls._on_stream(context, model, config, config.phase2_trajectories, "kkl/phase2")

    @classmethod
    def held_out(
        cls, context: FitContext, model: AutonomousModel, config: Phase2Config
    ) -> ForcedSamples:
        """Validation samples: a quarter as many forced trajectories (at least 4), of
        their own stream."""
        count = validation_count(config.phase2_trajectories)
        return cls._on_stream(context, model, config, count, "kkl/phase2/validation")

    @classmethod
    def _on_stream(cls, context, model, config, count: int, stream: str) -> ForcedSamples:
        data = observer_data(context, model.observer, FORCED_TRAINING, count, stream)
        return cls(data, sliding_windows(data.u, config.window))

    def draw(
        self, n: int, generator: torch.Generator, last_offset: int = 0
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Random (trajectory, step) indices, ``n`` of each, steps in the scored window
        leaving ``last_offset`` samples after them."""
        count, steps = self.windows.shape[:2]
        start = steady_state_start(steps)
        trajectory = draw_integers(count, (n,), generator)
        step = draw_integers(steps - last_offset, (n,), generator, low=start)
        return trajectory, step

    def tensor(self, name: str) -> torch.Tensor:
        """One of ``x``, ``z``, ``u``, ``y`` as a float32 tensor ``(n, steps, dim)`` (made once)."""
        if name not in self._tensors:
            self._tensors[name] = torch.as_tensor(getattr(self.data, name), dtype=torch.float32)
        return self._tensors[name]


VALIDATION_BATCHES = 16
"""Batches of held-out samples a Phase-2 validation loss averages (:func:`held_out_loss`):
enough that the best of a training's measurements is a choice among models, not among
draws of a few batches."""


def held_out_loss(
    batch_loss: Callable[[torch.Generator], torch.Tensor],
) -> Callable[[], float]:
    """A Phase-2 training's validation error: its loss on a batch of held-out samples
    (:meth:`ForcedSamples.held_out`) drawn from ``generator``, ``batch_loss(generator)``,
    averaged over :data:`VALIDATION_BATCHES` batches, the same batches at every call
    (drawn from a generator of their own)."""

    def error() -> float:
        generator = torch.Generator().manual_seed(0)
        with torch.no_grad():
            losses = [batch_loss(generator) for _ in range(VALIDATION_BATCHES)]
        return float(torch.stack(losses).mean())

    return error


def phase2_description(
    model: AutonomousModel, kind: str, config: Any, params: dict[str, Any], rule: PlateauRule
) -> dict[str, Any]:
    """The cache description of a Phase-2 model (``config``: its budget dataclass) on
    ``model``, trained under the plateau ``rule``."""
    return {
        "kind": kind,
        "phase1": model.description,
        "config": asdict(config),
        "params": params,
        "plateau": asdict(rule),
    }


def fit_phase2(
    context: FitContext,
    kind: str,
    params: dict[str, Any],
    pde_weight: float,
    build: Callable[[AutonomousModel, Phase2Config], nn.Module],
    train: Callable[
        [FitContext, AutonomousModel, Phase2Config, nn.Module, PlateauRule, torch.Generator],
        dict[str, Any],
    ],
) -> tuple[AutonomousModel, Phase2Config, nn.Module, dict[str, Any]]:
    """Phase 1 (shared, cached), then a Phase-2 module built and trained on it (cached).

    ``build(model, config)`` makes the module (under the run's seed);
    ``train(context, model, config, module, rule, generator)`` trains it under the
    profile's plateau ``rule``, drawing from ``generator`` only (see
    :func:`load_or_train`), and returns a log.
    Returns the Phase-1 model, the Phase-2 config, the module and the log.
    """
    model = fit_phase1(context, pde_weight)
    config = from_budget(Phase2Config, context)
    rule = from_budget(PlateauRule, context)
    with seeded(context.seed):
        module = build(model, config)
    description = phase2_description(model, kind, config, params, rule)
    log = load_or_train(
        context,
        description,
        module,
        lambda generator: train(context, model, config, module, rule, generator),
        uses=(model.encoder, model.decoder),
    )
    return model, config, module, log


def load_or_train(
    context: FitContext,
    description: dict[str, Any],
    modules: nn.Module,
    train: Callable[[torch.Generator], dict[str, Any]],
    uses: tuple[nn.Module, ...] = (),
) -> dict[str, Any]:
    """Load ``modules``' state from the cache, or call ``train(generator)`` and store it.

    ``train`` runs on ``context.device`` (:func:`kkl_bench.support.devices.training_on`), with
    ``modules`` and the other networks it ``uses`` moved there; the state is stored from
    the CPU.

    ``generator`` is seeded with the run's seed and is the only random generator
    ``train`` may draw from; the training is :func:`~kkl_bench.kkl.optimize.resumable`,
    so a killed run continues from its last checkpoint. ``train`` returns a dict of
    extra facts to store with the state (e.g. a training log); it is returned either
    way, with ``"spent"``: the optimizer steps and samples ``train`` took.
    """
    cache = CheckpointCache(context.cache_dir)
    kind = description["kind"]
    with cache.claim(kind, description):
        stored = cache.load(kind, description)
        if stored is None:
            generator = torch.Generator().manual_seed(context.seed)
            with resumable(context.cache_dir, description, [generator]):
                with (
                    counting() as spent,
                    training_on(context.device, modules, *uses) as spent.device,
                ):
                    log = train(generator)
                stored = {"state": modules.state_dict(), "log": {**log, "spent": spent.as_dict()}}
                cache.save(kind, description, stored)
    modules.load_state_dict(stored["state"])
    log = dict(stored["log"])
    modules.requires_grad_(False)
    return log
