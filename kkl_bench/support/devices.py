"""Where torch estimators train: ``--device auto|cpu|cuda``.

Only training moves. Models are stored in the cache as CPU tensors (any
machine loads them, with or without a GPU) and ``estimate`` always runs on
the CPU: an observer steps small networks one sample at a time, where a GPU's
launch latency costs more than its arithmetic saves. Random draws come from
CPU generators on every device, so a model trained on a GPU saw the same
samples, in the same order, as one trained on the CPU; the two differ by
floating-point rounding only. On the CPU, :func:`training_on` changes nothing.
"""

from __future__ import annotations

import functools
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext

import numpy as np
import torch
from torch import nn

from kkl_bench.support.device_names import check_device


def resolve(name: str) -> str:
    """The torch device ``name`` means on this machine: ``"cpu"`` or ``"cuda"``."""
    available = torch.cuda.is_available()
    if check_device(name) == "auto":
        return "cuda" if available else "cpu"
    if name == "cuda" and not available:
        raise ValueError(
            "device 'cuda' was asked for, but torch sees no CUDA GPU on this machine "
            "(torch.cuda.is_available() is False); use --device cpu or --device auto"
        )
    return name


@contextmanager
def training_on(device: str, *modules: nn.Module) -> Iterator[str]:
    """Inside the block, ``modules`` live on ``device`` (``auto``, ``cpu`` or ``cuda``) and
    torch's factories (``as_tensor``, ``zeros``, ...) create tensors there; after it, the
    modules are back on the CPU, also when the block raises. Yields the resolved device."""
    device = resolve(device)
    if device == "cpu":
        yield device
        return
    for module in modules:
        module.to(device)
    try:
        with torch.device(device):
            yield device
    finally:
        for module in modules:
            module.to("cpu")


def draw_integers(
    high: int, size: tuple[int, ...], generator: torch.Generator, low: int = 0
) -> torch.Tensor:
    """Integers in ``[low, high)`` of shape ``size`` from ``generator``, on the generator's
    device (the same draws wherever training runs; they index tensors on any device)."""
    return torch.randint(low, high, size, generator=generator, device=generator.device)


def draw_normal(size: torch.Size, generator: torch.Generator, like: torch.Tensor) -> torch.Tensor:
    """Standard normal numbers of shape ``size`` from ``generator``, on ``like``'s device."""
    return torch.randn(size, generator=generator, device=generator.device).to(like.device)


def to_numpy(tensor: torch.Tensor) -> np.ndarray:
    """A float64 numpy copy of ``tensor``, from any device."""
    return tensor.detach().double().cpu().numpy()


_FORCES_EAGER = hasattr(torch.compiler, "set_stance")
"""Whether this torch can run compiled functions eagerly on demand (2.6 and later)."""


@functools.cache
def compile_failure() -> str | None:
    """Why ``torch.compile`` cannot compile for this machine's CPU, or None when it can.

    Compiling for the CPU needs a C++ compiler (torch's inductor backend writes C++);
    a tiny function is compiled and run once per process to find out. The reason is
    the error's type and first line. Torch before 2.6 cannot run a compiled function
    eagerly on demand (``torch.compiler.set_stance``), which counting flops needs
    (:func:`kkl_bench.support.flops.counting`), so it does not compile either.
    """
    if not _FORCES_EAGER:
        return f"torch {torch.__version__} has no torch.compiler.set_stance (added in 2.6)"
    try:
        torch.compile(_double_plus_one, fullgraph=True, dynamic=False)(torch.ones(2))
    except Exception as error:  # any failure means: train eagerly
        first_line = next(iter(str(error).splitlines()), "")
        return f"{type(error).__name__}: {first_line}"
    return None


def _double_plus_one(x: torch.Tensor) -> torch.Tensor:
    return 2.0 * x + 1.0


def running_compiled_code_eagerly() -> AbstractContextManager:
    """A context in which functions compiled with ``torch.compile`` run eagerly (a no-op
    before torch 2.6, where nothing here is compiled: :func:`compile_failure`)."""
    return torch.compiler.set_stance("force_eager") if _FORCES_EAGER else nullcontext()
