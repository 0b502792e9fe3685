"""One Adam loop for every KKL training phase: clipping, cosine schedule, progress bar."""

from __future__ import annotations

from collections.abc import Callable, Iterable

import torch
from tqdm import tqdm


def minimize(
    loss_fn: Callable[[int], torch.Tensor],
    parameters: Iterable[torch.nn.Parameter],
    steps: int,
    lr: float = 1e-3,
    description: str = "training",
) -> list[float]:
    """Run ``steps`` Adam steps on ``loss_fn(step)``; returns the loss of every step.

    Gradients are clipped to norm 1 and the learning rate decays along a
    cosine to 1 % of ``lr``.
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
    return losses
