"""Phase 1: the autonomous KKL observer every KKL plugin starts from.

1. Choose the latent rates: for each candidate range, train a small decoder
   on observer data and keep the range with the lowest validation RMSE
   (validation trajectories come from their own training stream).
2. Train the encoder ``T`` on settled pairs ``(x, z)`` plus ``pde_weight``
   times the autonomous PDE residual ``dT/dx f - A T - B h`` at jittered
   states (JVP; residual in normalized latent units, divided by the RMS
   normalized vector field), validated by the same loss on the settled
   states of the validation trajectories.
3. Freeze ``T``; train the decoder ``T*`` on the observer's own latent states
   over the scored window: what it sees at test time. (Adding pairs
   ``(T(x), x)`` at the collocation states, as earlier versions did, changed
   validation RMSE by under 2 % on Duffing; they are gone.) It is validated on
   unforced and forced validation trajectories alike (its RMSE over both): the
   rows built on it are scored under inputs, and a decoder chosen on unforced
   trajectories alone got worse under inputs as it trained longer.

Both trainings end by the plateau rule (:mod:`kkl_bench.kkl.plateau`) and keep
their best state on validation; the brief trainings of step 1 only compare the
candidates and run a fixed number of steps.

The result is cached under a key of everything that determines it, so the
four KKL plugins (and reruns) share one Phase-1 model per system and seed.
The training checkpoints itself (:func:`kkl_bench.kkl.optimize.resumable`):
a Phase 1 that is killed continues from its last checkpoint when rerun.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

import numpy as np
import torch

from kkl_bench.estimator import FitContext
from kkl_bench.kkl.boxes import training_boxes
from kkl_bench.kkl.cache import CheckpointCache
from kkl_bench.kkl.config import from_budget
from kkl_bench.kkl.data import (
    Box,
    ObserverData,
    burn_in_steps,
    observer_data,
    validation_count,
)
from kkl_bench.kkl.decoder import decoder_rmse, train_decoder
from kkl_bench.kkl.latent import (
    LatentObserver,
    latent_drift,
    latent_matrices,
    spread_eigenvalues,
)
from kkl_bench.kkl.networks import NormalizedMLP, seeded
from kkl_bench.kkl.optimize import Training, counting, minimize, resumable
from kkl_bench.kkl.pde import normalized_field_rms, pde_residual
from kkl_bench.kkl.plateau import PlateauRule
from kkl_bench.protocol import PROTOCOL_ID
from kkl_bench.protocol.signals import InputFamily
from kkl_bench.registry import regimes
from kkl_bench.support.devices import draw_integers, draw_normal, to_numpy, training_on
from kkl_bench.training import FORCED_TRAINING

TOOLKIT_VERSION = 7
"""Bump when a change to this module changes what a given configuration trains."""

RATE_CANDIDATES = ((1.0, 5.0), (2.0, 10.0), (5.0, 20.0), (10.0, 40.0))
"""Candidate (slowest, fastest) latent rates in 1/s, geometrically spaced over n_z."""


@dataclass(frozen=True)
class Phase1Config:
    """Everything that determines a Phase-1 model (with the system, seed and protocol).

    Built from the profile's budget with :func:`kkl_bench.kkl.config.from_budget`.
    """

    hidden: int = 64
    depth: int = 3
    train_trajectories: int = 32
    encoder_steps: int = 2000
    decoder_steps: int = 2000
    selection_steps: int = 500
    batch: int = 1024
    pde_weight: float = 1.0
    rate_candidates: tuple[tuple[float, float], ...] = RATE_CANDIDATES
    jitter: float = 0.02
    train_box: str = "auto"
    """Where the unforced training trajectories start (see :func:`training_boxes`):
    ``"protocol"``: the x0 box only; ``"covering"``: half of them in a box
    covering the states that forced training trajectories reach; ``"auto"``:
    ``"covering"`` if forced training states leave the range of unforced ones,
    else ``"protocol"``."""


@dataclass
class AutonomousModel:
    """A trained autonomous KKL observer: latent observer, encoder ``T``, decoder ``T*``."""

    rates: np.ndarray
    observer: LatentObserver
    encoder: NormalizedMLP
    decoder: NormalizedMLP
    selection: dict[str, float] = field(default_factory=dict)
    description: dict = field(default_factory=dict)
    """The cache description that determines this model (extended by later phases' keys)."""
    quality: dict[str, float] = field(default_factory=dict)
    """Map-quality numbers on held-out training-stream states (see :func:`map_quality`)."""
    spent: dict[str, int] = field(default_factory=dict)
    """Optimizer steps and samples Phase 1 took (rate selection, encoder, decoder)."""
    training_log: dict = field(default_factory=dict)
    """The encoder's and the decoder's training logs with their validation curves."""

    def report(self) -> dict:
        """What a KKL plugin records with its results: toolkit version, rates, their
        selection, map quality."""
        report = {
            "toolkit": self.description.get("toolkit"),
            "latent_rates": self.rates.tolist(),
            "rate_selection": self.selection,
            "map_quality": self.quality,
        }
        if self.training_log:
            report["phase1_log"] = self.training_log
        return report

    def decode(self, z: np.ndarray) -> np.ndarray:
        """``T*(z)``: ``z: (..., n_z)`` -> ``(..., n_x)`` (float64 numpy).

        Samples are decoded :data:`DECODE_CHUNK` at a time: a block's hidden activations
        stay in cache (a million samples at once spend most of their time in memory).
        """
        flat = torch.as_tensor(np.reshape(z, (-1, np.shape(z)[-1])), dtype=torch.float32)
        with torch.no_grad():
            x_hat = torch.cat([self.decoder(part) for part in flat.split(DECODE_CHUNK)])
        return to_numpy(x_hat).reshape(*np.shape(z)[:-1], -1)

    def estimate(self, y: np.ndarray) -> np.ndarray:
        """Input-ignoring estimates ``(batch, steps, n_x)`` from ``y: (batch, steps, n_y)``."""
        return self.decode(self.observer.run(y))


DECODE_CHUNK = 8192
"""Samples per decoder call at test time. Decoding 1000 test trajectories (1001 samples
each, one thread, side by side): 1.36 us per sample at once, 0.43-0.55 in blocks of
4096-16384 (Duffing's 64-wide decoder); 3.5 against 1.4-1.6 (Lorenz's 128-wide one);
the same numbers."""


def _networks(n_x: int, n_z: int, config: Phase1Config) -> tuple[NormalizedMLP, NormalizedMLP]:
    return NormalizedMLP(n_x, n_z, config.hidden, config.depth), NormalizedMLP(
        n_z, n_x, config.hidden, config.depth
    )


def _tensor(array: np.ndarray) -> torch.Tensor:
    return torch.as_tensor(array, dtype=torch.float32)


def _select_rates(
    context: FitContext,
    config: Phase1Config,
    train_inputs: InputFamily,
    boxes: list[Box],
    generator: torch.Generator,
) -> tuple[np.ndarray, dict[str, float], ObserverData]:
    """The candidate rate range with the lowest validation RMSE of a briefly trained decoder
    (validation trajectories start in the protocol's x0 box, on their own stream), the
    score of each range, and the validation data observed with the chosen rates."""
    system = context.system
    scores = {}
    best = None
    for slowest, fastest in config.rate_candidates:
        rates = spread_eigenvalues(system.n_z, slowest, fastest)
        observer = LatentObserver(*latent_matrices(rates, system.n_y), context.dt)
        train = observer_data(
            context, observer, train_inputs, config.train_trajectories, "kkl/select", boxes
        )
        validation = observer_data(
            context,
            observer,
            train_inputs,
            validation_count(config.train_trajectories),
            "kkl/validation",
        )
        x, z = (_tensor(a) for a in train.scored())
        with seeded(context.seed):
            decoder = NormalizedMLP(system.n_z, system.n_x, config.hidden, config.depth)
        decoder.to(z.device).set_normalization(z, x)
        train_decoder(
            decoder,
            z,
            x,
            config.selection_steps,
            config.batch,
            generator,
            f"{system.name}: rates {slowest:g}-{fastest:g}",
        )
        x_val, z_val = validation.scored()
        rmse = decoder_rmse(decoder, _tensor(z_val), x_val)()
        scores[f"{slowest:g}-{fastest:g}"] = rmse
        if best is None or rmse < best[0]:
            best = (rmse, rates, validation)
    return best[1], scores, best[2]


VALIDATION_STATES = 8192
"""Settled validation states the encoder's validation loss is evaluated at (at most,
evenly spaced over all of them)."""


def _train_encoder(
    context: FitContext,
    config: Phase1Config,
    rule: PlateauRule,
    encoder: NormalizedMLP,
    data: ObserverData,
    validation: ObserverData,
    rates: np.ndarray,
    generator: torch.Generator,
) -> Training:
    """Fit ``T`` to settled pairs plus the PDE at jittered settled states; its validation
    error is the same loss at the settled states of the ``validation`` trajectories
    (:data:`VALIDATION_STATES` of them, not jittered)."""
    system = context.system
    burn_in = burn_in_steps(rates, context.dt)
    x, z = (_tensor(a) for a in data.settled(burn_in))
    encoder.set_normalization(x, z)
    a, b = (_tensor(m) for m in latent_matrices(rates, system.n_y))
    collocation = x + config.jitter * x.std(0) * draw_normal(x.shape, generator, x)
    vector_field, h_collocation = system.f(collocation), system.h(collocation)
    field_scale = normalized_field_rms(encoder, vector_field)

    def pairs_loss(x, z, states, field, h):
        """The data term on pairs ``(x, z)`` plus the weighted PDE residual at ``states``
        (where the vector field is ``field`` and the output ``h``)."""
        data_term = encoder.output_difference(encoder(x) - z).pow(2).sum(-1).mean()
        residual = pde_residual(encoder, states, field, h, a, b)
        normalized = encoder.output_difference(residual) / field_scale
        return data_term + config.pde_weight * normalized.pow(2).sum(-1).mean()

    def loss(_):
        rows = draw_integers(len(x), (config.batch,), generator)
        points = draw_integers(len(collocation), (config.batch,), generator)
        return pairs_loss(
            x[rows], z[rows], collocation[points], vector_field[points], h_collocation[points]
        )

    x_val, z_val = (_tensor(a).to(x.device) for a in validation.settled(burn_in))
    every = max(1, len(x_val) // VALIDATION_STATES)
    x_val, z_val = x_val[::every][:VALIDATION_STATES], z_val[::every][:VALIDATION_STATES]
    at_validation = (x_val, system.f(x_val), system.h(x_val))

    def validation_loss() -> float:
        with torch.no_grad():
            return float(pairs_loss(x_val, z_val, *at_validation))

    return minimize(  # each step draws `batch` data pairs and `batch` collocation points
        loss,
        encoder.parameters(),
        config.encoder_steps,
        2 * config.batch,
        description=f"{system.name}: encoder T",
        validation=validation_loss,
        rule=rule,
    )


def _train_phase1(
    context: FitContext,
    config: Phase1Config,
    rule: PlateauRule,
    encoder: NormalizedMLP,
    decoder: NormalizedMLP,
    generator: torch.Generator,
) -> tuple[np.ndarray, dict[str, float], dict]:
    """Choose the latent rates, then train ``encoder`` and ``decoder`` in place; every
    random draw of the training comes from ``generator``.

    Returns the rates, the validation score of each candidate range and the encoder's
    and decoder's training logs (the decoder's validation curve: RMSE on the rate
    selection's unforced validation trajectories and as many forced ones, observed with
    the chosen rates).
    """
    system = context.system
    unforced = regimes.get("zero")()
    boxes = training_boxes(context, config)
    rates, selection, validation = _select_rates(context, config, unforced, boxes, generator)
    observer = LatentObserver(*latent_matrices(rates, system.n_y), context.dt)
    data = observer_data(
        context, observer, unforced, config.train_trajectories, "kkl/phase1", boxes
    )
    encoding = _train_encoder(context, config, rule, encoder, data, validation, rates, generator)
    x, z = (_tensor(a) for a in data.scored())
    decoder.set_normalization(z, x)
    forced = observer_data(
        context, observer, FORCED_TRAINING, len(validation.x), "kkl/validation/forced"
    )
    x_val, z_val = (
        np.concatenate(pair) for pair in zip(validation.scored(), forced.scored(), strict=True)
    )
    training = train_decoder(
        decoder,
        z,
        x,
        config.decoder_steps,
        config.batch,
        generator,
        f"{system.name}: decoder T*",
        validation=(_tensor(z_val).to(z.device), x_val),
        rule=rule,
    )
    return rates, selection, {"encoder": encoding.log(), "decoder": training.log()}


def phase1_rule(context: FitContext) -> PlateauRule:
    """The plateau rule that ends Phase 1's encoder and decoder trainings: the profile's
    (:func:`from_budget`), with the budget's ``phase1_plateau_patience`` as its patience
    where the profile sets one (protocol 6.5: Phase 1's validation errors move most
    between measurements at the first learning rate)."""
    rule = from_budget(PlateauRule, context)
    patience = context.budget.get("phase1_plateau_patience")
    return rule if patience is None else replace(rule, plateau_patience=patience)


def fit_autonomous(
    context: FitContext, config: Phase1Config, rule: PlateauRule | None = None
) -> AutonomousModel:
    """Train (or load from the cache) the Phase-1 model for ``context.system``; its
    trainings end by ``rule`` (default: the profile's for Phase 1, :func:`phase1_rule`)."""
    system = context.system
    rule = rule or phase1_rule(context)
    description = {
        "kind": "kkl-phase1",
        "toolkit": TOOLKIT_VERSION,
        "protocol": PROTOCOL_ID,
        "system": system.name,
        "system_params": system.params(),
        "seed": context.seed,
        "config": asdict(config),
        "plateau": asdict(rule),
        **context.measurement.cache_entry(),
    }
    cache = CheckpointCache(context.cache_dir)
    with seeded(context.seed):
        encoder, decoder = _networks(system.n_x, system.n_z, config)
    with cache.claim("kkl-phase1", description):
        stored = cache.load("kkl-phase1", description)
        if stored is None:
            generator = torch.Generator().manual_seed(context.seed)
            with resumable(context.cache_dir, description, [generator]):
                with (
                    counting() as spending,
                    training_on(context.device, encoder, decoder) as spending.device,
                ):
                    rates, selection, log = _train_phase1(
                        context, config, rule, encoder, decoder, generator
                    )
                stored = {
                    "encoder": encoder.state_dict(),
                    "decoder": decoder.state_dict(),
                    "rates": torch.as_tensor(rates),
                    "selection": selection,
                    "log": log,
                    "spent": spending.as_dict(),
                }
                cache.save("kkl-phase1", description, stored)  # before the checkpoints go
    encoder.load_state_dict(stored["encoder"])
    decoder.load_state_dict(stored["decoder"])
    rates = stored["rates"].numpy()
    selection = dict(stored["selection"])
    spent = dict(stored["spent"])
    for network in (encoder, decoder):
        network.requires_grad_(False)
    observer = LatentObserver(*latent_matrices(rates, system.n_y), context.dt)
    model = AutonomousModel(
        rates,
        observer,
        encoder,
        decoder,
        selection,
        description,
        spent=spent,
        training_log=dict(stored.get("log", {})),
    )
    model.quality = map_quality(context, model)
    return model


def map_quality(context: FitContext, model: AutonomousModel, n: int = 8) -> dict[str, float]:
    """How well ``T`` solves the PDE and ``T*`` inverts it, on held-out states.

    States are the settled samples of ``n`` unforced and ``n`` forced
    trajectories from the x0 box (their own training streams). Returns
    ``reconstruction_rmse_{unforced,forced}``: RMS of ``|x - T*(T(x))|`` (state
    units), and ``pde_residual_{unforced,forced}``: RMS of the autonomous PDE
    residual ``dT/dx f - A T - B h`` relative to the RMS of ``A T + B h``.
    These bound what any observer built on the two maps can reach.
    """
    system = context.system
    a, b = (_tensor(m) for m in (model.observer.a, model.observer.b))
    quality = {}
    for label, inputs in (("unforced", regimes.get("zero")()), ("forced", FORCED_TRAINING)):
        data = observer_data(context, model.observer, inputs, n, f"kkl/quality/{label}")
        x = _tensor(data.scored()[0])
        with torch.no_grad():
            reconstruction = model.decoder(model.encoder(x)) - x
            residual = pde_residual(model.encoder, x, system.f(x), system.h(x), a, b)
            target = latent_drift(model.encoder(x), a) + system.h(x) @ b.T
        quality[f"reconstruction_rmse_{label}"] = reconstruction.pow(2).sum(-1).mean().sqrt().item()
        quality[f"pde_residual_{label}"] = (
            (residual.pow(2).sum(-1).mean() / target.pow(2).sum(-1).mean()).sqrt().item()
        )
    return quality


def fit_phase1(context: FitContext, pde_weight: float) -> AutonomousModel:
    """:func:`fit_autonomous` with the profile's budget and the estimator's ``pde_weight``."""
    return fit_autonomous(context, from_budget(Phase1Config, context, pde_weight=pde_weight))
