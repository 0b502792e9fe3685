"""Curriculum KKL: the autonomous observer with its decoder fine-tuned on forced data of
increasing spectral difficulty (the paper's adaptive-curriculum baseline).

Levels, easiest first: constant inputs; sinusoids with w in [0.2, 0.8] rad/s;
sinusoids with w in [0.8, 2.5] rad/s; square waves with P in [2, 10] s;
mixtures of 2-4 sinusoids. Only the decoder ``T*`` is trained (``A``, ``B``
and ``T`` stay as in Phase 1), on pairs (latent state of the input-ignoring
observer, true state) over the scored window: what ``T*`` sees at test time.
Each level is one training from lr 1e-3 (the rate restarts at each level) that
ends by the plateau rule (:mod:`kkl_bench.kkl.plateau`) on the decoder's RMSE on
the level's own validation trajectories, at most ``curriculum_steps`` steps, and
hands its best state to the next level; no unforced data are replayed (as in the
paper).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import torch

from kkl_bench.kkl.autonomous import fit_phase1
from kkl_bench.kkl.config import from_budget
from kkl_bench.kkl.data import observer_data, validation_count
from kkl_bench.kkl.decoder import train_decoder
from kkl_bench.kkl.estimator import KKLEstimator
from kkl_bench.kkl.phase2 import Phase2Config, load_or_train, phase2_description
from kkl_bench.kkl.plateau import PlateauRule
from kkl_bench.registry import estimators
from kkl_bench.training import ConstantFamily, MultiSineFamily, SineFamily, SquareFamily

LEVELS = (
    ("constant", ConstantFamily(1.0)),
    ("sine 0.2-0.8 rad/s", SineFamily((0.2, 0.8))),
    ("sine 0.8-2.5 rad/s", SineFamily((0.8, 2.5))),
    ("square 2-10 s", SquareFamily((2.0, 10.0))),
    ("multi-sine", MultiSineFamily((0.2, 2.5))),
)


@dataclass(frozen=True)
class CurriculumConfig:
    """The curriculum's budget (read with :func:`kkl_bench.kkl.config.from_budget`)."""

    curriculum_steps: int = 8000
    """The cap of each level's training (Adam steps)."""
    curriculum_batch: int = 1024


@estimators.register("curriculum_kkl")
class CurriculumKKL(KKLEstimator):
    """Autonomous observer whose decoder is fine-tuned level by level on forced data.

    Parameters
    ----------
    pde_weight: weight of the PDE residual in Phase 1 (shared with ``autonomous_kkl``).
    """

    name = "curriculum_kkl"

    def __init__(self, pde_weight: float = 1.0) -> None:
        self.pde_weight = pde_weight

    def fit_model(self, context):
        model = copy.deepcopy(fit_phase1(context, self.pde_weight))
        data_config = from_budget(Phase2Config, context)
        config = from_budget(CurriculumConfig, context)
        rule = from_budget(PlateauRule, context)
        description = phase2_description(
            model, "kkl-curriculum", data_config, {**self.get_params(), **config.__dict__}, rule
        )
        self.log_ = load_or_train(
            context,
            description,
            model.decoder,
            lambda generator: self._train(context, model, data_config, config, rule, generator),
        )
        self.model_ = model

    @staticmethod
    def _train(context, model, data_config, config, rule, generator) -> dict:
        """Train the decoder level by level; per level, its training log (the validation
        curve of the decoder's RMSE on the level's own validation trajectories)."""
        decoder = model.decoder
        decoder.requires_grad_(True)
        log = {}
        for index, (level, family) in enumerate(LEVELS):
            count = data_config.phase2_trajectories
            train = observer_data(context, model.observer, family, count, f"kkl/curriculum/{index}")
            x, z = (torch.as_tensor(a, dtype=torch.float32) for a in train.scored())
            x_val, z_val = observer_data(
                context,
                model.observer,
                family,
                validation_count(count),
                f"kkl/curriculum/{index}/validation",
            ).scored()
            log[level] = train_decoder(
                decoder,
                z,
                x,
                config.curriculum_steps,
                config.curriculum_batch,
                generator,
                f"{context.system.name}: curriculum {level}",
                validation=(torch.as_tensor(z_val, dtype=torch.float32), x_val),
                rule=rule,
            ).log()
        return log

    def estimate(self, t, y, u):
        self.check_fitted()
        return self.model_.estimate(y)
