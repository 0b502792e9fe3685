"""Static HyperKKL: the autonomous maps plus a learned input injection in the latent dynamics.

The observer is ``dz/dt = A z + B y + phi(z, c_t)`` with
``phi = u_t * psi(z, c_t)``: exactly zero when ``u_t = 0``, by construction.
``c_t`` is an LSTM embedding of the input window ``u[t-w, t]``. For these
control-affine systems the ideal injection is ``dT/dx(x) g u`` (one encoder
JVP along ``g``), which is ``psi``'s training target at ``z = T(x)`` on forced
training states. Between samples the injection is held (exponential Euler).

The default is the paper's observer (gain 1). With ``guard=True`` (our
variant, not in the paper; published as ``static_hyperkkl[guard=True]``)
the learned injection is scaled by a gain in [0, 1] chosen on forced
validation trajectories of a training stream
(:func:`kkl_bench.kkl.gain.select_gain`): ``psi`` learns the encoder's
Jacobian, and where that Jacobian is poor (Van der Pol, Lorenz) the full
injection is worse than none. Both share one trained ``psi`` (the guard
acts after training).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from kkl_bench.kkl.estimator import KKLEstimator
from kkl_bench.kkl.frozen import FrozenMLP
from kkl_bench.kkl.gain import select_gain
from kkl_bench.kkl.optimize import minimize
from kkl_bench.kkl.pde import directional_derivative
from kkl_bench.kkl.phase2 import ForcedSamples, fit_phase2, held_out_loss
from kkl_bench.kkl.windows import WindowEncoder, embed, sliding_windows
from kkl_bench.registry import estimators
from kkl_bench.support.devices import draw_normal


class Injection(nn.Module):
    """``psi(z, c)`` in normalized latent units: ``(n, n_z) x (n, context) -> (n, n_z)``."""

    def __init__(self, n_z: int, context: int, hidden: int) -> None:
        super().__init__()
        self.window_encoder = WindowEncoder(context)
        self.body = nn.Sequential(
            nn.Linear(n_z + context, hidden),
            nn.SiLU(),
            nn.Linear(hidden, hidden),
            nn.SiLU(),
            nn.Linear(hidden, n_z),
        )

    def forward(self, z_tilde: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        return self.body(torch.cat([z_tilde, context], dim=-1))


@estimators.register("static_hyperkkl")
class StaticHyperKKL(KKLEstimator):
    """Autonomous ``T``, ``T*`` plus ``phi = u psi(z, LSTM(u window))`` trained on ``dT/dx g``.

    Parameters
    ----------
    pde_weight: weight of the PDE residual in Phase 1 (shared with ``autonomous_kkl``).
    injection_hidden: width of ``psi``'s two hidden layers.
    guard: scale the injection by a gain chosen on validation data (see the module).
    """

    name = "static_hyperkkl"

    def __init__(
        self, pde_weight: float = 1.0, injection_hidden: int = 64, guard: bool = False
    ) -> None:
        self.pde_weight = pde_weight
        self.injection_hidden = injection_hidden
        self.guard = guard

    def fit_model(self, context):
        self.model_, self.config_, self.injection_, self.log_ = fit_phase2(
            context,
            "kkl-static",
            {"pde_weight": self.pde_weight, "injection_hidden": self.injection_hidden},
            self.pde_weight,
            lambda model, config: Injection(
                context.system.n_z, config.lstm_hidden, self.injection_hidden
            ),
            self._train,
        )
        self.gain_ = 1.0
        if self.guard:
            self.gain_, scores = select_gain(
                context,
                self.model_,
                self._injection,
                max(1, self.config_.phase2_trajectories // 2),
                "kkl/static/validation",
            )
            self.log_ = {**self.log_, "injection_gain": self.gain_, "gain_selection": scores}

    @staticmethod
    def _train(context, model, config, injection, rule, generator) -> dict:
        """Fit ``psi`` to the encoder's derivative along ``g``; the log records the loss on
        held-out forced samples as the validation curve."""
        encoder = model.encoder
        g = torch.as_tensor(context.system.g, dtype=torch.float32)

        def batch_loss(samples: ForcedSamples, generator: torch.Generator) -> torch.Tensor:
            trajectory, step = samples.draw(config.phase2_batch, generator)
            states = samples.tensor("x")[trajectory, step]
            with torch.no_grad():
                z, dz_along_g = directional_derivative(encoder, states, g.expand_as(states))
                z_tilde = encoder.normalized_output(z)
                z_tilde = z_tilde + 0.02 * draw_normal(z_tilde.shape, generator, z_tilde)
                target = encoder.output_difference(dz_along_g)
            contexts = injection.window_encoder(samples.windows[trajectory, step])
            return (injection(z_tilde, contexts) - target).pow(2).sum(-1).mean()

        samples = ForcedSamples.simulate(context, model, config)
        held_out = ForcedSamples.held_out(context, model, config)
        return minimize(
            lambda _: batch_loss(samples, generator),
            injection.parameters(),
            config.phase2_steps,
            config.phase2_batch,
            description=f"{context.system.name}: injection psi",
            validation=held_out_loss(lambda generator: batch_loss(held_out, generator)),
            rule=rule,
        ).log()

    def _injection(self, u: np.ndarray, gain: float):
        """``injection(k, z_k) = gain u_k psi(z_k, c_k)`` (latent units) for ``u: (batch, steps, 1)``.

        ``psi`` runs as a :class:`FrozenMLP` in physical latent units; the
        window embeddings ``c_k`` are computed (once per distinct window), and
        multiplied by ``psi``'s first layer, once for all samples, and only where
        ``gain u_k`` is non-zero (elsewhere the injection is zero whatever ``c_k`` is).
        """
        encoder = self.model_.encoder
        layers = [layer for layer in self.injection_.body if isinstance(layer, nn.Linear)]
        psi, context_weight = (
            FrozenMLP.from_layers(layers)
            .before_affine(encoder.out_coloring, torch.zeros(encoder.out_coloring.shape[0]))
            .split_input(encoder.out_mean.shape[0])
        )
        psi = psi.after_affine(encoder.out_mean, encoder.out_whitening)
        forced = (u[..., 0] != 0) & (gain != 0)  # (batch, steps)
        windows = sliding_windows(u, self.config_.window)[torch.as_tensor(forced)]
        offsets = np.zeros((*forced.shape, context_weight.shape[1]), dtype=np.float32)
        offsets[forced] = embed(self.injection_.window_encoder, windows).numpy() @ context_weight
        forced_step = forced.any(axis=0)

        def injection(k, z):
            if not forced_step[k]:
                return np.zeros_like(z)
            return gain * u[:, k] * psi(z, offsets[:, k])

        return injection

    def estimate(self, t, y, u):
        self.check_fitted()
        return self.model_.decode(self.model_.observer.run(y, self._injection(u, self.gain_)))
