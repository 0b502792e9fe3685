"""The EKF and the UKF unrolled: one trajectory's step in scalars, vectorized over the batch.

The generic kernels (:mod:`kkl_bench.estimators.filters.kalman_kernels`) take any system and
any size, and pay for it with a loop per operation and a call per model function at
every step. For a system of a few states measured through one output, the kernels here
are written for that system: its model's functions and the filter's algorithm are traced
(:mod:`kkl_bench.protocol.scalar_source`) into the straight-line arithmetic of one
trajectory's predict and update. :data:`LANES` copies of that code, one per trajectory,
interleaved statement by statement, run over the batch in blocks of :data:`LANES`, their
states in registers from sample to sample, and LLVM's SLP vectorizer packs the copies
into vector instructions. The traced operations are the generic kernel's, in its order,
so the estimates are bit-identical to it (``tests/test_unrolled_kernels.py``), and
through it equal the reference engine's (protocol 6.3).

A kernel's source is written to ``unrolled_kernels/`` under the cache directory, named
by its hash, and compiled with numba's on-disk cache, so a process that needs a kernel
another already compiled loads it. :func:`unrollable` says which models get one; the
others run the generic kernels.

Shapes: the kernels take ``y: (batch, steps, 1)`` and ``u: (batch, steps)`` and fill
``estimates: (batch, steps, n_x)``, NaN where a trajectory has stopped.
"""

from __future__ import annotations

import contextlib
import functools
import re

import numba
import numpy as np
from kkl_bench.estimators.filters.unrolled_model import (
    Traced,
    traced_rk4_step,
    traced_rk4_step_jacobian,
)

from kkl_bench.protocol.compiled import CompiledModel
from kkl_bench.protocol.scalar_source import (
    CHOOSE,
    Program,
    Scalar,
    UntraceableError,
    loaded,
    scalars,
    source_of,
)
from kkl_bench.support.cache import default_cache_dir, import_generated

MAX_STATES = 3
"""The largest system unrolled: a step's code grows as ``n^3`` (decision of this project;
protocol 6.3)."""


def unrollable(model: CompiledModel | None) -> bool:
    """Whether the filters run an unrolled kernel on ``model``: a built-in system of at
    most :data:`MAX_STATES` states with one output, whose functions trace into straight-line
    code (Chua's piecewise-linear drift branches on the state: it does not)."""
    if model is None or model.n_x > MAX_STATES or model.n_y != 1:
        return False
    try:
        _source(ekf_source, model, robust=True, inflated=True)
    except UntraceableError:
        return False
    return True


def _matmul(a, b):
    """``a @ b`` summed as ``kalman_linalg.matmul`` does (from 0.0, in order)."""
    out = np.empty((a.shape[0], b.shape[1]), dtype=object)
    for i in range(a.shape[0]):
        for j in range(b.shape[1]):
            total = 0.0
            for m in range(a.shape[1]):
                total = total + a[i, m] * b[m, j]
            out[i, j] = total
    return out


def _matmul_transposed(a, b):
    """``a @ b^T`` (``kalman_linalg.matmul_transposed``)."""
    return _matmul(a, b.T)


def _huber_noise(program: Program, R, residual, S, threshold):
    """``kalman_kernels._huber_noise`` for one output: ``R`` over Huber's weight."""
    normalized = program.let(f"abs({source_of(residual)}) / math.sqrt({source_of(S)})")
    weight = program.select(
        f"{normalized.name} > 0.0", program.let(f"{threshold} / {normalized.name}"), "math.inf"
    )
    smaller = program.select(f"{weight.name} < 1.0", weight, 1.0)  # min(1.0, weight)
    return program.let(f"{source_of(R)} / {smaller.name}")


def _inflated(program: Program, P, Q):
    """``inflation (P - Q) + Q`` entry by entry (``kalman_linalg.inflate``)."""
    inflation = program.named("inflation")
    return np.vectorize(lambda p, q: inflation * (p - q) + q, otypes=[object])(P, Q)


def _ekf_predict(program: Program, model: Traced, x, P, inflated: bool):
    """The EKF's predict at one trajectory (``kalman_kernels.ekf``, ``k > 0``)."""
    F = traced_rk4_step_jacobian(model, x)
    x = model.constrain(traced_rk4_step(model, x))
    Q = scalars(program, "Q", P.shape)
    P = _matmul_transposed(_matmul(F, P), F) + Q
    return x, _inflated(program, P, Q) if inflated else P


def _measured(program: Program, alive: str) -> None:
    """``measured``: the lane runs (``alive``) and has its measurement at this sample."""
    program.lines.append(f"measured = {alive} & math.isfinite(y_k_0)")


def _stop_singular(program: Program, invertible: Scalar, alive: str) -> None:
    """``running``: the lane goes on (it stops before a sample whose innovation covariance
    is singular); ``taken``: it takes this sample's update (``kalman_kernels._stop_singular``)."""
    program.lines.append(f"running = {alive} & ({invertible.name} | (not measured))")
    program.lines.append(f"taken = measured & {invertible.name}")


def _invert(program: Program, S: Scalar) -> tuple[Scalar, Scalar]:
    """``(S^-1, invertible)`` of one output's innovation variance
    (``kalman_linalg.invert_each``); ``S^-1`` is 0.0 where ``S`` is 0.0."""
    invertible = program.let(f"{S.name} != 0.0")
    return program.select(invertible, program.let(f"1.0 / {S.name}"), 0.0), invertible


def _ekf_update(program: Program, model: Traced, x, P, robust: bool):
    """The EKF's update at one trajectory for one output (``kalman_kernels.ekf``): the
    updated ``(x, P)``, which the lane keeps where ``taken``."""
    n = model.n
    _measured(program, "alive")
    H = model.sensed_output_jacobian(x)
    PHT = _matmul_transposed(P, H)
    S = _matmul(H, PHT)
    innovation = program.named("y_k_0") - model.sensed_output(x)[0]
    R = program.named("R_0_0")
    R_used = _huber_noise(program, R, innovation, S[0, 0] + R, "threshold") if robust else R
    SI, invertible = _invert(program, S[0, 0] + R_used)
    K = _matmul(PHT, np.array([[SI]], dtype=object))
    _stop_singular(program, invertible, "alive")
    x = np.array([x[i] + (0.0 + K[i, 0] * innovation) for i in range(n)], dtype=object)
    I_KH = np.array(
        [
            [(1.0 if i == j else 0.0) - (0.0 + K[i, 0] * H[0, j]) for j in range(n)]
            for i in range(n)
        ],
        dtype=object,
    )
    KR = np.array([[0.0 + K[i, 0] * R_used] for i in range(n)], dtype=object)
    P = _matmul_transposed(_matmul(I_KH, P), I_KH) + _matmul_transposed(KR, K)
    return x, P


def _upper_cholesky(program: Program, matrix):
    """``(root, definite)``: ``kalman_linalg.upper_cholesky`` and ``positive_definite`` at one
    trajectory (a NaN diagonal where ``matrix`` is not positive definite)."""
    n = len(matrix)
    root = np.full((n, n), 0.0, dtype=object)
    for j in range(n):
        diagonal = matrix[j, j]
        for k in range(j):
            diagonal = diagonal - root[k, j] * root[k, j]
        positive = program.let(f"{diagonal.name} > 0.0")
        root[j, j] = program.select(positive, program.call("math.sqrt", diagonal), "math.nan")
        for i in range(j + 1, n):
            total = matrix[j, i]
            for k in range(j):
                total = total - root[k, j] * root[k, i]
            root[j, i] = total / root[j, j]
    definite = " & ".join(f"(not math.isnan({root[j, j].name}))" for j in range(n))
    return root, program.let(definite)


def _sigma_points(program: Program, x, P):
    """Merwe's ``2 n + 1`` sigma points of ``(x, P)`` (``kalman_kernels._sigma_points``):
    ``(points: (2 n + 1, n), definite)``."""
    n = len(x)
    spread = program.named("spread")
    root, definite = _upper_cholesky(program, np.vectorize(lambda v: spread * v)(P))
    points = np.empty((2 * n + 1, n), dtype=object)
    points[0] = x
    for k in range(n):
        for i in range(n):
            points[k + 1, i] = x[i] - -root[k, i]
            points[n + k + 1, i] = x[i] - root[k, i]
    return points, definite


def _unscented_transform(program: Program, points, noise):
    """``(mean, covariance)`` of ``points: (count, size)`` with filterpy's weights ``Wm_i,
    Wc_i`` (``kalman_kernels._unscented_transform``)."""
    count, size = points.shape
    Wm, Wc = scalars(program, "Wm", (count,)), scalars(program, "Wc", (count,))
    mean = np.empty(size, dtype=object)
    for j in range(size):
        total = 0.0
        for i in range(count):
            total = total + Wm[i] * points[i, j]
        mean[j] = total
    residuals = np.array([[points[i, j] - mean[j] for j in range(size)] for i in range(count)])
    covariance = np.empty((size, size), dtype=object)
    for a, c in np.ndindex(size, size):
        total = 0.0
        for i in range(count):
            total = total + residuals[i, a] * (Wc[i] * residuals[i, c])
        covariance[a, c] = total + noise[a, c]
    return mean, covariance


def _ukf_predict(program: Program, model: Traced, x, P, inflated: bool):
    """The UKF's predict at one trajectory (``kalman_kernels.ukf``, ``k > 0``); defines
    ``alive_drawn``, whether the lane still runs once its sigma points are drawn."""
    points, definite = _sigma_points(program, x, P)
    program.lines.append(f"alive_drawn = alive & (first | {definite.name})")
    propagated = np.array([model.constrain(traced_rk4_step(model, point)) for point in points])
    Q = scalars(program, "Q", P.shape)
    x, P = _unscented_transform(program, propagated, Q)
    return x, _inflated(program, P, Q) if inflated else P


def _ukf_update(program: Program, model: Traced, x, P, robust: bool):
    """The UKF's update at one trajectory for one output (``kalman_kernels.ukf``), from
    sigma points redrawn from the prior ``(x, P)``."""
    n = model.n
    points, definite = _sigma_points(program, x, P)
    program.lines.append(f"alive_prior = alive_drawn & {definite.name}")
    _measured(program, "alive_prior")
    outputs = np.array([model.sensed_output(point) for point in points])
    R = scalars(program, "R", (1, 1))
    zp, S = _unscented_transform(program, outputs, R)
    y = program.named("y_k_0")
    if robust:
        R_used = _huber_noise(program, R[0, 0], y - zp[0], S[0, 0], "threshold")
        zp, S = _unscented_transform(program, outputs, np.array([[R_used]], dtype=object))
    SI, invertible = _invert(program, S[0, 0])
    _stop_singular(program, invertible, "alive_prior")
    Pxz = np.full((n, 1), 0.0, dtype=object)
    Wc = scalars(program, "Wc", (len(points),))
    for i in range(len(points)):
        for a in range(n):
            dx = points[i, a] - x[a]
            Pxz[a, 0] = Pxz[a, 0] + Wc[i] * (dx * (outputs[i, 0] - zp[0]))
    K = _matmul(Pxz, np.array([[SI]], dtype=object))
    x = np.array([x[a] + (0.0 + K[a, 0] * (y - zp[0])) for a in range(n)], dtype=object)
    KS = _matmul(K, S)
    P = np.array(
        [[P[a, c] - (0.0 + KS[a, 0] * K[c, 0]) for c in range(n)] for a in range(n)],
        dtype=object,
    )
    return x, P


def _sample(model: CompiledModel, predict, update, robust: bool, inflated: bool) -> list[str]:
    """One trajectory's sample as lines: ``predict(program, traced, x, P, inflated)``
    (skipped at the first sample, where ``first``), then ``update(program, traced, x, P,
    robust)``, then the state carried to the next sample, the estimate recorded while the
    lane runs, and the lane stopped where its estimate stops being finite."""
    n = model.n_x
    program = Program()
    traced = Traced(program, model)
    x, P = scalars(program, "x", (n,)), scalars(program, "P", (n, n))
    first = program.named("first")
    x_predicted, P_predicted = predict(program, traced, x, P, inflated)
    x_prior = np.array([program.select(first, *pair) for pair in zip(x, x_predicted, strict=True)])
    P_prior = np.array(
        [
            [program.select(first, *pair) for pair in zip(*rows, strict=True)]
            for rows in zip(P, P_predicted, strict=True)
        ]
    )
    x_new, P_new = update(program, traced, x_prior, P_prior, robust)
    lines = ["u_k = u[b, k - 1]", "y_k_0 = y[b, k, 0]", *program.lines]
    for i in range(n):
        lines.append(f"x_{i} = choose(taken, {source_of(x_new[i])}, {source_of(x_prior[i])})")
    for i, j in np.ndindex(n, n):
        new, old = source_of(P_new[i, j]), source_of(P_prior[i, j])
        lines.append(f"P_{i}_{j} = choose(taken, {new}, {old})")
    for i in range(n):
        lines.append(f"estimates[b, k, {i}] = choose(running, x_{i}, math.nan)")
    finite = " & ".join(f"math.isfinite(x_{i})" for i in range(n))
    lines.append(f"alive = running & {finite}")
    return lines


LANES = 4
"""Trajectories one kernel iteration advances together, one per float64 lane of an AVX2
vector register; the batch is padded to a multiple of it."""


def _interleaved(lines: list[str], copies: int) -> list[str]:
    """``copies`` copies of a lane's ``lines``, interleaved line by line: copy ``c`` has
    its locals suffixed ``_c`` and runs on the trajectory ``b{c}``."""
    bound = {line.split(" = ")[0] for line in lines if re.match(r"^\w+ = ", line)}
    local = re.compile(r"\b(" + "|".join(sorted(bound, key=len, reverse=True)) + r")\b")
    out = []
    for line in lines:
        for copy in range(copies):
            renamed = local.sub(lambda match, c=copy: f"{match.group(1)}_{c}", line)
            out.append(renamed.replace("[b, ", f"[b{copy}, "))
    return out


def _module(model: CompiledModel, sample: list[str], weights: list[str] | None = None) -> str:
    """A kernel module: ``kernel(p, s, g, y, u, dt, x0, P0, Q, R, [Wm, Wc, spread,]
    inflation, threshold, estimates)`` runs ``sample`` (:func:`_sample`) at every sample of
    :data:`LANES` trajectories at a time, their states in registers; ``weights``: the
    lines reading the UKF's ``Wm`` and ``Wc`` into locals."""
    n = model.n_x
    head = [
        "batch, steps = u.shape",
        "half = 0.5 * dt",
        "sixth = dt / 6.0",
        *loaded("p", "p", model.p.shape),
        *loaded("s", "s", model.s.shape),
        *loaded("g", "g", model.g.shape),
        *loaded("Q", "Q", (n, n)),
        *loaded("R", "R", (1, 1)),
        *(weights or []),
    ]
    arguments = ["Q", "R", *(["Wm", "Wc", "spread"] if weights else []), "inflation", "threshold"]
    start = [f"x_{i} = x0[{i}]" for i in range(n)]
    start += [f"P_{i}_{j} = P0[{i}, {j}]" for i, j in np.ndindex(n, n)]
    start += ["alive = True"]
    block = [f"b{c} = {LANES} * block + {c}" for c in range(LANES)]
    block += _interleaved(start, LANES)
    block += ["for k in range(steps):", "    first = k == 0"]
    block += [f"    {line}" for line in _interleaved(sample, LANES)]
    loops = [f"for block in range(batch // {LANES}):", *(f"    {line}" for line in block)]
    signature = ", ".join(["p", "s", "g", "y", "u", "dt", "x0", "P0", *arguments, "estimates"])
    return "\n".join(
        [
            '"""Generated by kkl_bench.estimators.filters.kalman_unrolled: do not edit."""',
            "import math",
            "",
            "import numba",
            "import numpy as np",
            "",
            "",
            CHOOSE,
            "",
            '@numba.njit(cache=True, error_model="numpy")',
            f"def kernel({signature}):",
            *(f"    {line}" for line in head + loops),
            "",
        ]
    )


def ekf_source(model: CompiledModel, robust: bool, inflated: bool) -> str:
    """The source of the unrolled EKF on ``model`` (:func:`run_ekf`)."""
    return _module(model, _sample(model, _ekf_predict, _ekf_update, robust, inflated))


def ukf_source(model: CompiledModel, robust: bool, inflated: bool) -> str:
    """The source of the unrolled UKF on ``model`` (:func:`run_ukf`)."""
    count = 2 * model.n_x + 1
    return _module(
        model,
        _sample(model, _ukf_predict, _ukf_update, robust, inflated),
        weights=[*loaded("Wm", "Wm", (count,)), *loaded("Wc", "Wc", (count,))],
    )


@contextlib.contextmanager
def _slp_vectorizer():
    """Compile with LLVM's SLP vectorizer, which packs the :data:`LANES` interleaved
    copies of a step into vector instructions. numba turns it off by default since 0.57
    for miscompilations reported in other code (numba PR 8852); the unrolled kernels are
    checked bit for bit against the generic ones (``tests/test_unrolled_kernels.py``)."""
    previous = numba.config.SLP_VECTORIZE
    numba.config.SLP_VECTORIZE = 1
    try:
        yield
    finally:
        numba.config.SLP_VECTORIZE = previous


@functools.cache
def _kernel(source: str):
    return import_generated(source, default_cache_dir() / "unrolled_kernels", "kalman").kernel


_SOURCES: dict[tuple, str] = {}
"""Each kernel's source by what it is traced from (tracing takes milliseconds)."""


def _source(source_function, model: CompiledModel, robust: bool, inflated: bool) -> str:
    """``source_function(model, robust, inflated)``, traced once per process."""
    key = (source_function, model.functions, tuple(model.q), model.p.shape, model.s.shape)
    key += (model.g.shape, robust, inflated)
    if key not in _SOURCES:
        _SOURCES[key] = source_function(model, robust, inflated)
    return _SOURCES[key]


def _run(source_function, model: CompiledModel, y, u, dt, x0, P0, arguments, settings, out):
    """Run the kernel ``source_function(model, robust, inflated)`` writes:
    ``y: (batch, steps, 1)``, ``u: (batch, steps)``, ``settings``: ``(inflation,
    threshold)``; fills ``out: (batch, steps, n_x)`` (C-ordered). A batch that is not a
    multiple of :data:`LANES` is padded with unmeasured trajectories."""
    inflation, threshold = settings
    source = _source(source_function, model, bool(np.isfinite(threshold)), inflation != 1.0)
    batch, steps, _ = y.shape
    padded = -(-batch // LANES) * LANES
    estimates = out
    if padded != batch:
        y = np.concatenate([y, np.full((padded - batch, steps, 1), np.nan)])
        u = np.concatenate([u, np.zeros((padded - batch, steps))])
        estimates = np.empty((padded, steps, model.n_x))
    with _slp_vectorizer():
        _kernel(source)(
            model.p, model.s, model.g, y, u, dt, x0, P0, *arguments, *settings, estimates
        )
    if padded != batch:
        out[...] = estimates[:batch]


def run_ekf(model: CompiledModel, y, u, dt, x0, P0, Q, R, inflation, threshold, out) -> None:
    """``kalman_kernels.ekf`` on ``model`` (:func:`unrollable`), unrolled (:func:`_run`)."""
    _run(ekf_source, model, y, u, dt, x0, P0, (Q, R), (inflation, threshold), out)


def run_ukf(
    model: CompiledModel, y, u, dt, x0, P0, Q, R, Wm, Wc, spread, inflation, threshold, out
) -> None:
    """``kalman_kernels.ukf`` on ``model`` (:func:`unrollable`), unrolled (:func:`_run`)."""
    arguments = (Q, R, Wm, Wc, spread)
    _run(ukf_source, model, y, u, dt, x0, P0, arguments, (inflation, threshold), out)
