"""Injection KKL: the stationary KKL observer with the exact input injection (beyond the paper).

For a control-affine system ``dx/dt = f(x) + g u``, if ``T`` solves the
autonomous PDE then ``z = T(x)`` obeys ``dz/dt = A z + B y + dT/dx(x) g u``
(the paper's stationary approach; Bernard and Andrieu 2019). With learned
maps the injection is evaluated at the decoded estimate,
``phi_k = dT/dx(T*(z_k)) g u_k``: one forward-mode JVP of the encoder along
``g``. The linear part is integrated exactly over each sample (first-order
hold of ``y``) and ``phi_k`` is held over the step (exponential Euler).

The maps are the cached Phase-1 ``T`` and ``T*`` of ``autonomous_kkl``. The
learned maps are never exact, so with ``adapt`` (the default) two steps
follow, both on training streams:

1. the injection is scaled by a gain in [0, 1], the one of
   ``injection_gains`` with the lowest RMSE on forced validation
   trajectories (:func:`kkl_bench.kkl.gain.select_gain`): an encoder whose
   Jacobian is poor (Lorenz) then does less harm;
2. a copy of ``T*`` is fine-tuned on the latent states this observer itself
   produces along forced and unforced training trajectories
   (``adaptation_rounds`` rounds, since those states depend on the decoder
   through the injection). Each round ends by the plateau rule on the
   decoder's RMSE on the latent states the observer produces along validation
   trajectories, and the decoder kept is the one, of the rounds' and Phase 1's,
   with the lowest RMSE of the injected observer on those trajectories.

Without ``adapt`` (the pure stationary observer, gain 1), zero input gives
exactly ``autonomous_kkl``.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
import torch

from kkl_bench.estimator import FitContext
from kkl_bench.kkl.autonomous import AutonomousModel, fit_phase1
from kkl_bench.kkl.config import from_budget
from kkl_bench.kkl.data import validation_count
from kkl_bench.kkl.decoder import train_decoder
from kkl_bench.kkl.estimator import KKLEstimator
from kkl_bench.kkl.frozen import FrozenMLP
from kkl_bench.kkl.gain import GAINS, select_gain, simulate_families
from kkl_bench.kkl.phase2 import load_or_train, phase2_description
from kkl_bench.kkl.plateau import PlateauRule
from kkl_bench.protocol.metrics import rmse, steady_state_start
from kkl_bench.registry import estimators, regimes
from kkl_bench.training import FORCED_TRAINING


@dataclass(frozen=True)
class AdaptationConfig:
    """Budget of the adaptation (read with :func:`kkl_bench.kkl.config.from_budget`)."""

    adaptation_trajectories: int = 64
    """Training trajectories of each kind (unforced, forced); half as many validate the gain."""
    adaptation_steps: int = 16000
    """The cap of Adam steps over all rounds (a round's is its share)."""
    adaptation_rounds: int = 4
    injection_gains: tuple[float, ...] = GAINS
    batch: int = 1024


class ExactInjection:
    """``injection(k, z_k) = gain dT/dx(T*(z_k)) g u_k`` for :meth:`LatentObserver.run`.

    ``u: (batch, steps, 1)``; returns ``(batch, n_z)`` arrays. The maps run as
    :class:`FrozenMLP` copies of the current networks, and not at all where
    ``gain u_k`` is zero on every trajectory. Each ``T*(z_k)`` computed on the
    way is kept: it is that sample's estimate (:meth:`estimates`).
    """

    def __init__(self, model: AutonomousModel, g: np.ndarray, u: np.ndarray, gain: float = 1.0):
        self.model, self.u, self.gain = model, u, gain
        self.decoder, self.encoder = FrozenMLP.of(model.decoder), FrozenMLP.of(model.encoder)
        self.direction = np.asarray(g, dtype=np.float32)
        self.forced = u.any(axis=(0, 2)) & (gain != 0)
        self.decoded = np.empty((*u.shape[:2], len(self.direction)))

    def __call__(self, k: int, z: np.ndarray) -> np.ndarray:
        if not self.forced[k]:
            return np.zeros_like(z)
        x_hat = self.decoder(z)
        self.decoded[:, k] = x_hat
        _, along_g = self.encoder.with_tangent(x_hat, self.direction)
        return self.gain * self.u[:, k] * along_g

    def estimates(self, z: np.ndarray) -> np.ndarray:
        """``T*(z)`` for the latent trajectories ``z: (batch, steps, n_z)`` this injection
        drove: the kept ``T*(z_k)`` of the forced samples (equal to decoding them again up
        to float32 rounding), the others decoded now (``steps`` includes the last sample,
        which no injection sees). ``(batch, steps, n_x)``."""
        computed = self.forced.copy()
        computed[-1] = False
        x_hat = self.decoded
        x_hat[:, ~computed] = self.model.decode(z[:, ~computed])
        return x_hat


def adapt(
    context: FitContext,
    model: AutonomousModel,
    config: AdaptationConfig,
    rule: PlateauRule,
    generator: torch.Generator,
) -> dict:
    """Choose the injection gain, then fine-tune ``model.decoder`` in place on the
    injected observer's own latent states (batches drawn from ``generator``).

    Each round runs the observer (with the current decoder in the injection)
    on ``adaptation_trajectories`` unforced and as many forced training
    trajectories (:data:`~kkl_bench.training.FORCED_TRAINING`) and on their
    validation counterparts, then trains the decoder on the pairs ``(z_k, x_k)`` of
    the scored window under the plateau ``rule``. Returns the gain, its selection
    scores, each round's training log and ``rounds_curve``: the injected observer's
    validation RMSE before the first round and after each (``(steps, RMSE)``), whose
    lowest point gives the decoder kept (``best_round``, 0 for Phase 1's).
    """
    system = context.system
    gain, scores = select_gain(
        context,
        model,
        lambda u, gain: ExactInjection(model, system.g, u, gain),
        max(1, config.adaptation_trajectories // 2),
        "kkl/adapt/validation",
        config.injection_gains,
    )
    log = {"injection_gain": gain, "gain_selection": scores}
    families = {"unforced": regimes.get("zero")(), "forced": FORCED_TRAINING}
    x, y, u = simulate_families(context, families, config.adaptation_trajectories, "kkl/adapt")
    x_val, y_val, u_val = simulate_families(
        context, families, validation_count(config.adaptation_trajectories), "kkl/adapt/curve"
    )
    start = steady_state_start(x.shape[1])

    def scored(array: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(array[:, start:].reshape(-1, array.shape[-1]), dtype=torch.float32)

    def latent(y: np.ndarray, u: np.ndarray) -> np.ndarray:
        return model.observer.run(y, ExactInjection(model, system.g, u, gain))

    def injected_rmse(z_val: np.ndarray) -> float:  # the injected observer's validation RMSE
        return float(rmse(x_val, model.decode(z_val)).mean())

    model.decoder.requires_grad_(True)
    cap = config.adaptation_steps // config.adaptation_rounds
    states, states_val = scored(x), x_val[:, start:].reshape(-1, system.n_x)
    # the validation trajectories' latent states under the current decoder: they give the
    # injected observer's RMSE after a round and the next round's validation pairs
    z_val = latent(y_val, u_val)
    curve = [(0, injected_rmse(z_val))]
    best = (curve[0][1], 0, copy.deepcopy(model.decoder.state_dict()))
    for round_ in range(1, config.adaptation_rounds + 1):
        training = train_decoder(
            model.decoder,
            scored(latent(y, u)),
            states,
            cap,
            config.batch,
            generator,
            f"{system.name}: adapting T* ({round_}/{config.adaptation_rounds})",
            validation=(scored(z_val), states_val),
            rule=rule,
        )
        log[f"round {round_}"] = training.log()
        z_val = latent(y_val, u_val)
        curve.append((curve[-1][0] + len(training.losses), injected_rmse(z_val)))
        if curve[-1][1] < best[0]:
            best = (curve[-1][1], round_, copy.deepcopy(model.decoder.state_dict()))
    model.decoder.load_state_dict(best[2])
    return {**log, "rounds_curve": curve, "best_round": best[1]}


@estimators.register("injection_kkl")
class InjectionKKL(KKLEstimator):
    """``dz/dt = A z + B y + dT/dx(T*(z)) g u``, ``x_hat = T*(z)``, on the autonomous maps.

    Parameters
    ----------
    pde_weight: weight of the PDE residual in Phase 1 (shared with ``autonomous_kkl``).
    adapt: choose the injection gain and fine-tune ``T*`` on this observer's own
        latent states (see the module); ``False`` is the pure stationary observer.
    """

    name = "injection_kkl"

    def __init__(self, pde_weight: float = 1.0, adapt: bool = True) -> None:
        self.pde_weight = pde_weight
        self.adapt = adapt

    def fit_model(self, context):
        model = fit_phase1(context, self.pde_weight)
        self.gain_ = 1.0
        if self.adapt:
            model = copy.deepcopy(model)
            config = from_budget(AdaptationConfig, context)
            rule = from_budget(PlateauRule, context)
            description = phase2_description(
                model, "kkl-injection", config, self.get_params(), rule
            )
            self.log_ = load_or_train(
                context,
                description,
                model.decoder,
                lambda generator: adapt(context, model, config, rule, generator),
            )
            self.gain_ = self.log_["injection_gain"]
        self.model_ = model

    def estimate(self, t, y, u):
        context = self.check_fitted()
        injection = ExactInjection(self.model_, context.system.g, u, self.gain_)
        return injection.estimates(self.model_.observer.run(y, injection))
