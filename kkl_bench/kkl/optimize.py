"""One Adam loop for every KKL training phase: clipping, cosine schedule, progress bar,
and a ledger of the optimizer steps and samples every training spends."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass

import torch
from tqdm import tqdm


@dataclass
class Spent:
    """Training effort: optimizer steps and the training samples they drew.

    A *sample* is one example a loss evaluates: a (state, latent) pair, a
    PDE collocation point or an (input window, state) pair.
    """

    steps: int = 0
    samples: int = 0

    def as_dict(self) -> dict[str, int]:
        return {"steps": self.steps, "samples": self.samples}


_LEDGERS: ContextVar[tuple[Spent, ...]] = ContextVar("kkl_bench_ledgers", default=())


@contextmanager
def counting() -> Iterator[Spent]:
    """Count what every :func:`minimize` inside the block spends (nested blocks each count)."""
    spent = Spent()
    token = _LEDGERS.set((*_LEDGERS.get(), spent))
    try:
        yield spent
    finally:
        _LEDGERS.reset(token)


def minimize(
    loss_fn: Callable[[int], torch.Tensor],
    parameters: Iterable[torch.nn.Parameter],
    steps: int,
    samples_per_step: int,
    lr: float = 1e-3,
    description: str = "training",
) -> list[float]:
    """Run ``steps`` Adam steps on ``loss_fn(step)``; returns the loss of every step.

    ``samples_per_step`` is how many training samples one ``loss_fn`` call
    draws; with the steps it is recorded in every open :func:`counting`
    block. Gradients are clipped to norm 1 and the learning rate decays along
    a cosine to 1 % of ``lr``.
    """
    parameters = [p for p in parameters if p.requires_grad]
    optimizer = torch.optim.Adam(parameters, lr=lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(
        optimizer, max(steps, 1), eta_min=0.01 * lr
    )
    losses = []
    with tqdm(range(steps), desc=description, leave=False, disable=None, mininterval=1.0) as bar:
        for step in bar:
            optimizer.zero_grad(set_to_none=True)
            loss = loss_fn(step)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(parameters, 1.0)
            optimizer.step()
            schedule.step()
            losses.append(loss.item())
            if step % 100 == 0:
                bar.set_postfix(loss=f"{losses[-1]:.3g}")
    for spent in _LEDGERS.get():
        spent.steps += steps
        spent.samples += steps * samples_per_step
    return losses
