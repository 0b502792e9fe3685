"""One Adam loop for every learned training: clipping, the plateau rule, progress bar,
a ledger of the optimizer steps and samples every training spends, a validation curve,
and resumable checkpoints for long trainings.

A training given a validation error (an RMSE on validation trajectories of a
training stream, or its loss on held-out samples) and a
:class:`~kkl_bench.kkl.plateau.PlateauRule` measures the error before the first step
and every ``validate_every`` steps, lowers its learning rate on each plateau, stops on
the last one (or at its cap of steps) and ends with the parameters of its best
measurement (protocol section 6.5). Without a rule (a brief training that only
compares candidates) it runs its steps under a cosine schedule.

Inside a :func:`resumable` block every :func:`minimize` call is numbered and
writes its state (parameters, optimizer, schedule, losses, the block's random
generators) to the checkpoint cache every ``every`` steps and when it ends.
Rerun after a kill, the same block replays the calls that had finished from
their final checkpoints and continues the interrupted one from its last, so
the result is the same as that of an uninterrupted run for the same seed.
"""

from __future__ import annotations

import math
import statistics
import time
import warnings
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from kkl_bench.kkl.cache import CheckpointCache
from kkl_bench.kkl.plateau import PLATEAU, Plateau, PlateauRule
from kkl_bench.support import flops, status
from kkl_bench.support.cache import RESUME_KIND
from kkl_bench.support.convergence import converged
from kkl_bench.support.provenance import provenance

CHECKPOINT_EVERY = 500
"""Optimizer steps between two checkpoints of a resumable training."""


@dataclass
class Spent:
    """Training effort: optimizer steps, the training samples they drew, and time.

    A *sample* is one example a loss evaluates: a (state, latent) pair, a
    PDE collocation point or an (input window, state) pair. ``device`` is where the
    training ran (:mod:`kkl_bench.support.devices`). ``seconds`` is the
    wall time of the :func:`counting` block (data simulation included) and
    ``processor_seconds`` the processor time this process spent in it (its core-seconds:
    on one thread, unaffected by other load on the machine or a pause); a block
    inside a :func:`resumable` one that resumed from a checkpoint also counts the
    times the interrupted run had spent up to that checkpoint, so both read as those of
    the uninterrupted training. ``git_commit`` is the commit of the code that
    trained (``-dirty`` from a modified tree; :func:`kkl_bench.support.provenance.provenance`): it is
    stored with the model, so a cell scored from a cached model records which code trained
    it beside the commit that scored it.
    """

    steps: int = 0
    samples: int = 0
    seconds: float = 0.0
    processor_seconds: float = 0.0
    device: str = "cpu"
    git_commit: str | None = field(default_factory=lambda: provenance()["git_commit"])

    def as_dict(self) -> dict[str, float | str | None]:
        return {
            "steps": self.steps,
            "samples": self.samples,
            "seconds": self.seconds,
            "processor_seconds": self.processor_seconds,
            "device": self.device,
            "git_commit": self.git_commit,
        }


VALIDATION_POINTS = 10
"""Validation errors measured along a training without a plateau rule, besides the one
before its first step."""


@dataclass
class Training:
    """What one :func:`minimize` call did: the loss of every step; if it was given a
    validation error, ``validation``: ``(step, error)`` pairs, step 0 before training;
    under a plateau rule, ``plateau``: :meth:`Plateau.log` (why it stopped, the step of
    the parameters kept)."""

    losses: list[float]
    validation: list[tuple[int, float]] = field(default_factory=list)
    plateau: dict[str, Any] | None = None

    @property
    def kept_error(self) -> float:
        """The validation error of the parameters the training ended with: the best
        measurement's under a plateau rule, else the last."""
        return self.plateau["best_error"] if self.plateau else self.validation[-1][1]

    def log(self, last: int = 50) -> dict[str, Any]:
        """The training log a fit report records: the steps run, the mean loss of the
        ``last`` steps and, with a validation curve, the curve, the plateau rule's record
        and whether the training converged (stopped by the plateau; without a rule,
        :func:`~kkl_bench.support.convergence.converged` on the curve)."""
        log: dict[str, Any] = {
            "steps": len(self.losses),
            "final_loss": float(sum(self.losses[-last:]) / len(self.losses[-last:])),
        }
        if self.validation:
            log["validation_curve"] = [[step, error] for step, error in self.validation]
        if self.plateau is not None:
            log.update(self.plateau)
            log["converged"] = self.plateau["stopped"] == PLATEAU
        elif self.validation:
            log["converged"] = converged(self.validation)
        return log


_LEDGERS: ContextVar[tuple[Spent, ...]] = ContextVar("kkl_bench_ledgers", default=())


@contextmanager
def counting() -> Iterator[Spent]:
    """Count what every :func:`minimize` inside the block spends (nested blocks each count),
    and the block's wall and processor time."""
    spent = Spent()
    token = _LEDGERS.set((*_LEDGERS.get(), spent))
    resume = _RESUME.get()
    credit = dict(resume.credit) if resume else dict.fromkeys(CLOCKS, 0.0)
    start = _clocks()
    try:
        yield spent
    finally:
        now = _clocks()
        taken = {
            name: now[name] - start[name] + (resume.credit[name] if resume else 0.0) - credit[name]
            for name in CLOCKS
        }
        spent.seconds, spent.processor_seconds = taken["seconds"], taken["processor_seconds"]
        _LEDGERS.reset(token)


CLOCKS = ("seconds", "processor_seconds")
"""The times a training records (:class:`Spent`): wall and this process's processor time."""


def _clocks() -> dict[str, float]:
    """Each of :data:`CLOCKS` read now (s)."""
    return {"seconds": time.perf_counter(), "processor_seconds": time.process_time()}


@dataclass
class _Resume:
    """The checkpoints of one :func:`resumable` block."""

    cache: CheckpointCache
    description: dict[str, Any]
    generators: list[torch.Generator]
    every: int
    calls: int = 0
    written: list[dict[str, Any]] = field(default_factory=list)
    credit: dict[str, float] = field(default_factory=lambda: dict.fromkeys(CLOCKS, 0.0))
    """s added to the block's times (each of :data:`CLOCKS`): what the interrupted run had
    spent before the checkpoint it resumed from, less what this run took to get back
    there."""

    def __post_init__(self) -> None:
        self.started = _clocks()

    SLOTS = (0, 1)
    """Checkpoints alternate between two slots, so a kill while one is written
    leaves the other whole."""

    def next_call(self) -> dict[str, Any]:
        """The checkpoint description of the next :func:`minimize` call."""
        self.calls += 1
        call = {"training": self.description, "call": self.calls}
        self.written += [{**call, "slot": slot} for slot in self.SLOTS]
        return call

    def elapsed(self) -> dict[str, float]:
        """The times (s, each of :data:`CLOCKS`) of training behind the block's current
        state, as an uninterrupted run."""
        now = _clocks()
        return {name: now[name] - self.started[name] + self.credit[name] for name in CLOCKS}

    def save(self, call, step, parameters, optimizer, schedule, training) -> None:
        self.cache.save(
            RESUME_KIND,
            {**call, "slot": (step // self.every) % len(self.SLOTS)},
            {
                "step": step,
                "parameters": [p.detach().clone() for p in parameters],
                "optimizer": optimizer.state_dict(),
                "schedule": schedule.state_dict(),
                "losses": list(training.losses),
                "validation": list(training.validation),
                "generators": [g.get_state() for g in self.generators],
                **self.elapsed(),
            },
        )

    def restore(self, call, parameters, optimizer, schedule) -> tuple[int, Training]:
        """Load the call's newest whole checkpoint into the training state; the step it
        resumes from and the training so far."""
        slots = [self.cache.load(RESUME_KIND, {**call, "slot": slot}) for slot in self.SLOTS]
        stored = max((s for s in slots if s is not None), key=lambda s: s["step"], default=None)
        if stored is None:
            return 0, Training([])
        if len(stored["generators"]) != len(self.generators):
            warnings.warn(
                f"ignoring the checkpoint of {call['training'].get('kind', 'a training')} at "
                f"step {stored['step']}: it holds {len(stored['generators'])} random "
                f"generators, this training draws from {len(self.generators)} (written by "
                "another version); training from the start",
                stacklevel=2,
            )
            return 0, Training([])
        with torch.no_grad():
            for parameter, value in zip(parameters, stored["parameters"], strict=True):
                parameter.copy_(value)
        optimizer.load_state_dict(stored["optimizer"])
        schedule.load_state_dict(stored["schedule"])
        for generator, state in zip(self.generators, stored["generators"], strict=True):
            generator.set_state(state)
        elapsed = self.elapsed()
        for name in CLOCKS:  # each time the checkpoint's version recorded
            if name in stored:
                self.credit[name] += stored[name] - elapsed[name]
        validation = [tuple(point) for point in stored.get("validation", [])]
        return stored["step"], Training(list(stored["losses"]), validation)


_RESUME: ContextVar[_Resume | None] = ContextVar("kkl_bench_resume", default=None)


@contextmanager
def resumable(
    cache_dir: Path,
    description: dict[str, Any],
    generators: list[torch.Generator],
    every: int | None = None,
) -> Iterator[None]:
    """Checkpoint every :func:`minimize` call in the block (see the module).

    ``description`` identifies the training (as its cache key does);
    ``generators`` are every random generator the block's losses draw from;
    ``every`` defaults to :data:`CHECKPOINT_EVERY`. The checkpoints are
    removed when the block completes.
    """
    resume = _Resume(CheckpointCache(cache_dir), description, generators, every or CHECKPOINT_EVERY)
    token = _RESUME.set(resume)
    try:
        yield
    finally:
        _RESUME.reset(token)
    for written in resume.written:  # reached only when the block completed
        resume.cache.remove(RESUME_KIND, written)


def _adam_step(loss_fn, step, parameters, optimizer, schedule=None) -> float:
    """One optimizer step of :func:`minimize` on ``loss_fn(step)`` (then one step of a
    cosine ``schedule``, if given); returns the loss."""
    optimizer.zero_grad(set_to_none=True)
    loss = loss_fn(step)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(parameters, 1.0)
    optimizer.step()
    if schedule is not None:
        schedule.step()
    return loss.item()


@dataclass
class Probe:
    """Measures what each :func:`minimize` call inside :func:`probing` achieves instead of
    training: one step counted (:func:`kkl_bench.support.flops.counting`: the matrix products of
    the loss and its gradient), then one untimed, then ``steps`` steps timed, each the
    same work as a training step. ``records`` gets one entry per call: ``training`` (its
    description), ``samples_per_step``, ``fit_steps`` (the steps the training would run),
    ``steps``, ``seconds`` (``steps`` times the median of the timed steps: a compiled
    loss compiles a variant on the first step that needs it, which a fit pays once and
    the median leaves out) and ``flops_per_step``. A validation error,
    if the call has one, is measured before and after (untimed), so the fit that reads
    its curve goes on."""

    steps: int
    records: list[dict[str, Any]] = field(default_factory=list)

    def measure(self, loss_fn, parameters, optimizer, schedule, samples_per_step, steps,
                description, validation):  # fmt: skip
        curve = [(0, float(validation()))] if validation is not None else []
        with flops.counting() as counted:
            losses = [_adam_step(loss_fn, 0, parameters, optimizer, schedule)]
        # untimed: a compiled loss compiles on its first step
        losses.append(_adam_step(loss_fn, 1, parameters, optimizer, schedule))
        durations = []
        for step in range(2, self.steps + 2):
            start = time.perf_counter()
            losses.append(_adam_step(loss_fn, step, parameters, optimizer, schedule))
            durations.append(time.perf_counter() - start)
        self.records.append(
            {
                "training": description,
                "samples_per_step": samples_per_step,
                "fit_steps": steps,
                "steps": self.steps,
                "seconds": self.steps * statistics.median(durations),
                "flops_per_step": counted(),
            }
        )
        if validation is not None:
            curve.append((len(losses), float(validation())))
        return Training(losses, curve)


_PROBE: ContextVar[Probe | None] = ContextVar("kkl_bench_probe", default=None)


@contextmanager
def probing(steps: int) -> Iterator[Probe]:
    """Inside the block, every :func:`minimize` call runs ``2 + steps`` optimizer steps and
    is measured (:class:`Probe`), not trained: for throughput, never for a model to keep."""
    probe = Probe(steps)
    token = _PROBE.set(probe)
    try:
        yield probe
    finally:
        _PROBE.reset(token)


def minimize(
    loss_fn: Callable[[int], torch.Tensor],
    parameters: Iterable[torch.nn.Parameter],
    steps: int,
    samples_per_step: int,
    lr: float = 1e-3,
    description: str = "training",
    validation: Callable[[], float] | None = None,
    rule: PlateauRule | None = None,
) -> Training:
    """Adam on ``loss_fn(step)`` for at most ``steps`` steps; returns the loss of every
    step and the validation curve.

    ``samples_per_step`` is how many training samples one ``loss_fn`` call draws; with
    the steps run it is recorded in every open :func:`counting` block. Gradients are
    clipped to norm 1. ``validation()`` returns the current validation error and must
    draw from no generator the training draws from.

    With a plateau ``rule`` (which needs ``validation``) the learning rate starts at
    ``lr`` and the rule decides (:class:`~kkl_bench.kkl.plateau.Plateau`): the error is
    measured before the first step and every ``rule.validate_every`` steps, ``steps`` is
    the cap, and the parameters end at the best measurement. Without one the rate decays
    along a cosine to 1 % of ``lr`` over exactly ``steps`` steps, the error (if given) is
    measured every ``ceil(steps / VALIDATION_POINTS)`` steps, and the parameters are the
    last step's.
    """
    if rule is not None and validation is None:
        raise ValueError(f"{description}: a plateau rule needs a validation error")
    parameters = [p for p in parameters if p.requires_grad]
    optimizer = torch.optim.Adam(parameters, lr=lr)
    schedule = plateau = None
    if rule is None:
        schedule = torch.optim.lr_scheduler.CosineAnnealingLR(
            optimizer, max(steps, 1), eta_min=0.01 * lr
        )
        every = math.ceil(steps / VALIDATION_POINTS) if steps else 1
    else:
        plateau, every = Plateau(rule, parameters, optimizer), rule.validate_every
    probe = _PROBE.get()
    if probe is not None:
        return probe.measure(
            loss_fn, parameters, optimizer, schedule, samples_per_step, steps, description,
            validation,
        )  # fmt: skip
    resume = _RESUME.get()
    checkpoint = resume.next_call() if resume else None
    start, training = (0, Training([]))
    if resume:
        start, training = resume.restore(checkpoint, parameters, optimizer, schedule or plateau)
    if validation is not None and start == 0:
        _measure(training, 0, validation, plateau)
    with tqdm(
        total=steps, initial=start, desc=description, leave=False, disable=None, mininterval=1.0
    ) as bar:
        step = start
        while step < steps and not (plateau and plateau.stopped):
            training.losses.append(_adam_step(loss_fn, step, parameters, optimizer, schedule))
            step += 1
            bar.update()
            if step % 100 == 1:
                bar.set_postfix(loss=f"{training.losses[-1]:.3g}")
            status.step(description, step, steps)
            if validation is not None and (step % every == 0 or step == steps):
                _measure(training, step, validation, plateau)
            done = step == steps or (plateau and plateau.stopped)
            if resume and (step % resume.every == 0 or done):
                resume.save(checkpoint, step, parameters, optimizer, schedule or plateau, training)
    if plateau:
        plateau.reach_cap()
        plateau.restore_best()
        training.plateau = plateau.log()
    for spent in _LEDGERS.get():
        spent.steps += len(training.losses)
        spent.samples += len(training.losses) * samples_per_step
    return training


def _measure(
    training: Training, step: int, validation: Callable[[], float], plateau: Plateau | None
) -> None:
    """Append the validation error after ``step`` steps to the curve and let the
    ``plateau`` rule, if any, act on it."""
    error = float(validation())
    training.validation.append((step, error))
    if plateau is not None:
        plateau.measure(step, error)
