"""Sliding input windows ``u[k-w .. k]`` and their LSTM embedding.

Windows reaching before ``t = 0`` are zero-padded. A window is all zeros
exactly when the input was zero over it, which the hypernetwork plugins use
to return the autonomous observer's output exactly.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn


def sliding_windows(u: np.ndarray | torch.Tensor, window: int) -> torch.Tensor:
    """``u: (batch, steps, 1)`` -> windows ``(batch, steps, window + 1)``, the last entry ``u_k``."""
    u = torch.as_tensor(u, dtype=torch.float32)[..., 0]
    padded = nn.functional.pad(u, (window, 0))
    return padded.unfold(1, window + 1, 1)


class WindowEncoder(nn.Module):
    """LSTM over a window; its final hidden state is the context ``c``. ``(n, w+1) -> (n, hidden)``."""

    def __init__(self, hidden: int) -> None:
        super().__init__()
        self.lstm = nn.LSTM(1, hidden, batch_first=True)

    def forward(self, windows: torch.Tensor) -> torch.Tensor:
        _, (h, _) = self.lstm(windows.unsqueeze(-1))
        return h[-1]


def is_active(windows: torch.Tensor) -> torch.Tensor:
    """``(n, w+1) -> (n,)``: True where the window holds any non-zero input."""
    return windows.abs().amax(dim=-1) > 0
