"""Dynamic HyperKKL: input-window-conditioned weight perturbations of frozen ``T`` and ``T*``.

A shared LSTM embeds the window ``u[t-w, t]``; two heads emit perturbations
of every weight of the encoder and of the decoder (chunked full-rank by
default, as the paper's method section describes; ``head="lowrank"`` for its
implementation-details variant). The latent observer ignores the input, and
``x_hat_k = T*(z_k; phi_base + dphi(u window))``.

Phase-2 loss on forced training data, per window (several states each):
``|x - T*(z_obs; phi_t)|^2`` (the inference path) ``+ |x - T*(T(x; theta_t); phi_t)|^2``
``+ pde_weight |dT/dx (f(x) + g u_t) + [T(x; theta_{t+dt}) - T(x; theta_t)] / dt - A T - B h|^2``,
the paper's objective with its finite-difference time derivative. Weights
are generated once per window and applied to all of its states with
``baddbmm`` (at test time once per distinct window, which a constant or square
input repeats); the perturbation is ``G(c) - G(c_zero)``, and where a window is
exactly zero the base decoder is used, so zero input reproduces
``autonomous_kkl`` exactly.
"""

from __future__ import annotations

import torch
from torch import nn

from kkl_bench.kkl.estimator import KKLEstimator
from kkl_bench.kkl.hyper import make_head
from kkl_bench.kkl.latent import latent_drift
from kkl_bench.kkl.optimize import minimize
from kkl_bench.kkl.pde import directional_derivative, normalized_field_rms
from kkl_bench.kkl.phase2 import ForcedSamples, fit_phase2, held_out_loss
from kkl_bench.kkl.windows import WindowEncoder, distinct, encode, is_active, sliding_windows
from kkl_bench.registry import estimators
from kkl_bench.support.devices import draw_integers

INFERENCE_CHUNK = 512
"""Samples decoded at once at test time (bounds the memory of their generated weights)."""

SHARED_WINDOW = 8
"""Samples from which a window's generated weights are applied to all its samples in one
dense product rather than copied once per sample (a constant input shares 20 windows
over 90 % of a test set's samples, a square input 651 over a third)."""


class HyperNetwork(nn.Module):
    """Shared window LSTM and the encoder and decoder heads."""

    def __init__(
        self, encoder_shapes, decoder_shapes, context: int, head: str, chunk: int, rank: int
    ) -> None:
        super().__init__()
        self.window_encoder = WindowEncoder(context)
        self.encoder_head = make_head(head, encoder_shapes, context, chunk, rank)
        self.decoder_head = make_head(head, decoder_shapes, context, chunk, rank)

    def contexts(self, windows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Embeddings of ``windows: (n, w+1)`` and of the all-zero window (expanded to ``n``)."""
        both = self.window_encoder(torch.cat([windows, torch.zeros_like(windows[:1])]))
        return both[:-1], both[-1:].expand(len(windows), -1)


@estimators.register("dynamic_hyperkkl")
class DynamicHyperKKL(KKLEstimator):
    """Frozen autonomous ``T``, ``T*`` with hypernetwork weight perturbations from the input window.

    Parameters
    ----------
    pde_weight: weight of the PDE residuals (Phase 1 and Phase 2).
    head: ``"chunked"`` (full rank, default) or ``"lowrank"``.
    chunk: entries per generated chunk (chunked head).
    rank: rank of the perturbations (low-rank head).
    """

    name = "dynamic_hyperkkl"

    def __init__(
        self, pde_weight: float = 1.0, head: str = "chunked", chunk: int = 1024, rank: int = 32
    ) -> None:
        self.pde_weight = pde_weight
        self.head = head
        self.chunk = chunk
        self.rank = rank

    def fit_model(self, context):
        self.model_, self.config_, self.hyper_, self.log_ = fit_phase2(
            context,
            "kkl-dynamic",
            self.get_params(),
            self.pde_weight,
            lambda model, config: HyperNetwork(
                model.encoder.parameter_shapes(),
                model.decoder.parameter_shapes(),
                config.lstm_hidden,
                self.head,
                self.chunk,
                self.rank,
            ),
            self._train,
        )

    def _train(self, context, model, config, hyper, rule, generator) -> dict:
        """Fit the hypernetwork (see the module); the log records the loss on held-out
        forced samples as the validation curve."""
        system = context.system
        samples = ForcedSamples.simulate(context, model, config)
        held_out = ForcedSamples.held_out(context, model, config)
        pool, held_out_pool = _pool(samples), _pool(held_out)
        encoder, decoder = model.encoder, model.decoder
        a, b = (
            torch.as_tensor(m, dtype=torch.float32) for m in (model.observer.a, model.observer.b)
        )
        g = torch.as_tensor(system.g, dtype=torch.float32)
        field_scale = normalized_field_rms(encoder, system.f(pool))
        n_windows = max(1, config.phase2_batch // config.collocation_points)

        def batch_loss(
            samples: ForcedSamples, pool: torch.Tensor, generator: torch.Generator
        ) -> torch.Tensor:
            """The loss on a batch of ``samples``, collocation states drawn from ``pool``."""
            x, z_observed, u = samples.tensor("x"), samples.tensor("z"), samples.tensor("u")
            trajectory, step = samples.draw(n_windows, generator, last_offset=1)
            contexts, zero = hyper.contexts(
                torch.cat(
                    [samples.windows[trajectory, step], samples.windows[trajectory, step + 1]]
                )
            )
            theta_now = hyper.encoder_head(contexts[:n_windows], zero[:n_windows])
            theta_next = hyper.encoder_head(contexts[n_windows:], zero[n_windows:])
            phi_now = hyper.decoder_head(contexts[:n_windows], zero[:n_windows])
            others = pool[
                draw_integers(len(pool), (n_windows, config.collocation_points - 1), generator)
            ]
            states = torch.cat(
                [x[trajectory, step].unsqueeze(1), others], dim=1
            )  # (windows, points, n_x)
            field = system.f(states) + u[trajectory, step].unsqueeze(1) * g
            t_now, dt_field = directional_derivative(encoder, states, field, theta_now)
            t_next = encoder(states, theta_next)
            residual = (
                dt_field
                + (t_next - t_now) / context.dt
                - latent_drift(t_now, a)
                - system.h(states) @ b.T
            )
            reconstruction = decoder.output_difference(decoder(t_now, phi_now) - states)
            inference = decoder.output_difference(
                decoder(z_observed[trajectory, step].unsqueeze(1), phi_now) - states[:, :1]
            )
            normalized_residual = encoder.output_difference(residual) / field_scale
            return (
                inference.pow(2).sum(-1).mean()
                + reconstruction.pow(2).sum(-1).mean()
                + self.pde_weight * normalized_residual.pow(2).sum(-1).mean()
            )

        return minimize(
            lambda _: batch_loss(samples, pool, generator),
            hyper.parameters(),
            config.phase2_steps,
            n_windows * config.collocation_points,
            description=f"{system.name}: hypernetwork",
            validation=held_out_loss(
                lambda generator: batch_loss(held_out, held_out_pool, generator)
            ),
            rule=rule,
        ).log()

    def estimate(self, t, y, u):
        self.check_fitted()
        z = self.model_.observer.run(y)
        x_hat = self.model_.decode(z)
        windows = sliding_windows(u, self.config_.window).reshape(-1, self.config_.window + 1)
        active = torch.nonzero(is_active(windows))[:, 0]
        if active.numel() == 0:
            return x_hat
        rows, which = distinct(windows[active])
        contexts = encode(self.hyper_.window_encoder, rows)
        zero = encode(self.hyper_.window_encoder, torch.zeros_like(rows[:1]))
        flat_z = torch.as_tensor(z.reshape(-1, z.shape[-1]), dtype=torch.float32)
        flat_x = x_hat.reshape(-1, x_hat.shape[-1])
        counts = torch.bincount(which, minlength=len(rows))
        order = torch.argsort(which, stable=True)  # active samples grouped by window
        starts = torch.cumsum(counts, 0) - counts
        shared = torch.nonzero(counts >= SHARED_WINDOW)[:, 0]
        with torch.no_grad():
            # a window many samples share: its weights applied to all of them at once
            for part in _chunks(shared, INFERENCE_CHUNK // 8):
                deltas = self.hyper_.decoder_head(contexts[part], zero)
                for i, window in enumerate(part.tolist()):
                    samples = active[order[starts[window] : starts[window] + counts[window]]]
                    decoded = self.model_.decoder(
                        flat_z[samples].unsqueeze(0),
                        [(w[i : i + 1], b[i : i + 1]) for w, b in deltas],
                    )
                    flat_x[samples.numpy()] = decoded[0].double().numpy()
            # the others sample by sample, grouped by window: weights generated once per chunk
            rest = order[counts[which[order]] < SHARED_WINDOW]
            for part in _chunks(rest, INFERENCE_CHUNK):
                needed, local = torch.unique(which[part], return_inverse=True)
                deltas = self.hyper_.decoder_head(contexts[needed], zero)
                samples = active[part]
                decoded = self.model_.decoder(
                    flat_z[samples].unsqueeze(1), [(w[local], b[local]) for w, b in deltas]
                )
                flat_x[samples.numpy()] = decoded[:, 0].double().numpy()
        return x_hat


def _pool(samples: ForcedSamples) -> torch.Tensor:
    """The collocation states: every state of ``samples`` after the first 51 samples
    ``(count, n_x)``."""
    x = samples.tensor("x")
    return x[:, 51:].reshape(-1, x.shape[-1])


def _chunks(indices: torch.Tensor, size: int) -> tuple[torch.Tensor, ...]:
    """``indices`` in chunks of ``size``; none at all if it is empty."""
    return indices.split(size) if indices.numel() else ()
