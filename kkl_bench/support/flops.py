"""What a network row computes online, counted by its layer sizes (protocol 6.3).

Inside :func:`counting`, every matrix product the code runs is counted as ``2 m k n``
flops (an ``(m, k) @ (k, n)`` product), wherever it runs:

- in torch, by torch's own counter (``torch.utils.flop_counter.FlopCounterMode``,
  which sees each product a layer, a GRU cell or a generated weight performs);
- in an ``nn.LSTM``, which that counter does not see (one fused kernel), by its layer
  sizes (:func:`lstm_flops`; three times that where it is trained, for the backward);
- in the observers' numpy paths (:class:`~kkl_bench.kkl.frozen.FrozenMLP`, the latent
  observer's drive), which report their own products with :func:`add`.

Elementwise operations (activations, sums, a diagonal latent recursion) are not
counted: a few percent of a network's arithmetic, so a network's floor is, if anything,
low and its cost over the floor high. The filters count all of theirs
(``flops_per_step()``), where products do not dominate.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from contextvars import ContextVar

import torch
from torch import nn
from torch.utils.flop_counter import FlopCounterMode

from kkl_bench.support.devices import running_compiled_code_eagerly

_tally: ContextVar[list[float] | None] = ContextVar("kkl_bench_flop_tally", default=None)


def products(rows: int, inner: int, columns: int) -> float:
    """Flops of an ``(rows, inner) @ (inner, columns)`` matrix product."""
    return 2.0 * rows * inner * columns


def add(flops: float) -> None:
    """Add ``flops`` to the count of the enclosing :func:`counting` (nothing outside one)."""
    tally = _tally.get()
    if tally is not None:
        tally[0] += flops


def lstm_flops(lstm: nn.LSTM, samples: int) -> float:
    """The matrix products of ``lstm`` over ``samples`` (batch x steps) inputs: per layer
    and direction, the four gates from the input and from the hidden state
    (``2 * 4 h (n_in + h)`` a sample), and the projection if it has one."""
    directions = 2 if lstm.bidirectional else 1
    hidden = lstm.proj_size or lstm.hidden_size
    total = 0.0
    for layer in range(lstm.num_layers):
        n_in = lstm.input_size if layer == 0 else hidden * directions
        gates = products(samples, n_in + hidden, 4 * lstm.hidden_size)
        projection = products(samples, lstm.hidden_size, lstm.proj_size) if lstm.proj_size else 0
        total += directions * (gates + projection)
    return total


def _count_lstm(module: nn.Module, args: tuple, output) -> None:
    """Count an ``nn.LSTM``'s products; three times its forward ones where gradients will
    flow back through it (a product's backward is two products: the gradients of its
    input and of its weight)."""
    if isinstance(module, nn.LSTM):
        inputs = args[0]
        trained = torch.is_grad_enabled() and any(p.requires_grad for p in module.parameters())
        add((3 if trained else 1) * lstm_flops(module, inputs.numel() // module.input_size))


@contextlib.contextmanager
def counting() -> Iterator[Callable[[], float]]:
    """Count the matrix products run inside the block; yields a function that returns
    the count so far (and the total, after the block). Functions compiled with
    ``torch.compile`` run eagerly inside it (the counter cannot see into compiled code;
    they compute the same products)."""
    tally = [0.0]
    token = _tally.set(tally)
    hook = nn.modules.module.register_module_forward_hook(_count_lstm)
    counter = FlopCounterMode(display=False)
    try:
        with running_compiled_code_eagerly(), counter:
            yield lambda: tally[0] + counter.get_total_flops()
    finally:
        hook.remove()
        _tally.reset(token)


def counted(call: Callable[[], object]) -> float:
    """The matrix-product flops of ``call()`` (:func:`counting`)."""
    with torch.no_grad(), counting() as total:
        call()
    return total()
