"""The particle filter's building blocks: systematic resampling, Gaussian log densities and
the proposals (locally optimal, mixture, initial) each step draws particles from."""

from __future__ import annotations

import numpy as np
from scipy.linalg import solve_triangular
from scipy.special import logsumexp

from kkl_bench.protocol.system import System


def systematic_resample(weights: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Ancestor indices by systematic resampling, row by row.

    ``weights: (batch, n)`` normalised rows, ``offsets: (batch,)`` uniform in [0, 1)
    -> ``(batch, n)`` integer indices into each row.
    """
    n = weights.shape[1]
    cumulative = np.cumsum(weights, axis=1)
    cumulative[:, -1] = 1.0
    positions = (offsets[:, None] + np.arange(n)) / n
    # row by row, so that a trajectory's ancestors do not depend on the other rows
    ancestors = [
        np.searchsorted(c, x, side="right") for c, x in zip(cumulative, positions, strict=True)
    ]
    return np.minimum(np.array(ancestors, dtype=np.int64).reshape(weights.shape), n - 1)


def gaussian_log_density(residual: np.ndarray, variance: float) -> np.ndarray:
    """``log N(residual; 0, variance I)`` summed over the last axis."""
    dim = residual.shape[-1]
    return -0.5 * (np.sum(residual**2, axis=-1) / variance + dim * np.log(2 * np.pi * variance))


def _times(matrix, vector):
    """``(..., a, b) @ (..., b) -> (..., a)``, broadcasting."""
    return np.einsum("...ij,...j->...i", matrix, vector)


def _linearised(system: System, mean: np.ndarray) -> np.ndarray:
    """The Jacobian of ``h`` at ``mean``: ``(..., n_y, n_x)``, or one ``(n_y, n_x)`` matrix
    when it is the same for every particle (a linear ``h``)."""
    jacobian = system.h_jacobian(mean)
    n_y, n_x = jacobian.shape[-2:]
    first = jacobian.reshape(-1, n_y, n_x)[0]
    if np.array_equal(jacobian, np.broadcast_to(first, jacobian.shape)):
        return first
    return jacobian


class _GaussianProposal:
    """The optimal proposal of ``s`` given a Gaussian measurement of variance ``r``:
    ``N(mean + q H^T S^-1 e, (I/q + H^T H / r)^-1)`` with ``S = q H H^T + r I``,
    ``e = y - h(mean)`` (see :func:`optimal_proposal`)."""

    def __init__(self, jacobian, mean, innovation, q: float, r: float) -> None:
        n_y = jacobian.shape[-2]
        self.jacobian, self.mean, self.innovation, self.q, self.r = (
            jacobian,
            mean,
            innovation,
            q,
            r,
        )
        self.covariance = q * jacobian @ np.swapaxes(jacobian, -1, -2) + r * np.eye(n_y)
        self.gain = (
            q * np.swapaxes(jacobian, -1, -2) @ np.linalg.inv(self.covariance)
        )  # q H^T S^-1, (..., n_x, n_y)
        self.proposal_mean = mean + _times(self.gain, innovation)

    def sample(self, w: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Matheron's rule: ``mean + sqrt(q) w + q H^T S^-1 (e - H sqrt(q) w - sqrt(r) v)``."""
        process = np.sqrt(self.q) * w
        return (
            self.mean
            + process
            + _times(
                self.gain, self.innovation - _times(self.jacobian, process) - np.sqrt(self.r) * v
            )
        )

    def log_density(self, sample: np.ndarray) -> np.ndarray:
        """``log q(sample)``: ``(...)``; only ``n_y x n_y`` determinants (Sylvester)."""
        n_y, n_x = self.jacobian.shape[-2:]
        offset = sample - self.proposal_mean
        quadratic = (
            np.sum(offset**2, axis=-1) / self.q
            + np.sum(_times(self.jacobian, offset) ** 2, axis=-1) / self.r
        )
        log_det_precision = (
            np.linalg.slogdet(self.covariance)[1] - n_x * np.log(self.q) - n_y * np.log(self.r)
        )
        return 0.5 * (log_det_precision - quadratic - n_x * np.log(2 * np.pi))

    def log_marginal(self) -> np.ndarray:
        """``log N(e; 0, S)``: how likely the measurement is from ``mean``, ``(...)``."""
        n_y = self.jacobian.shape[-2]
        covariance = np.broadcast_to(self.covariance, (*self.innovation.shape, n_y))
        solved = np.linalg.solve(covariance, self.innovation[..., None])[..., 0]
        return -0.5 * (
            np.sum(self.innovation * solved, axis=-1)
            + np.linalg.slogdet(covariance)[1]
            + n_y * np.log(2 * np.pi)
        )


def optimal_proposal(
    system: System,
    mean: np.ndarray,
    y: np.ndarray,
    q: float,
    r: float,
    w: np.ndarray,
    v: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Draw the pre-constraint state from the (linearised) optimal proposal.

    ``mean: (..., n_x)`` transition means ``RK4(x_k, u_k)``, ``y: (..., n_y)``,
    ``w: (..., n_x)`` and ``v: (..., n_y)`` standard normal draws. Returns
    ``s: (..., n_x)`` and ``log q(s) - log N(s; mean, q I)``: ``(...)``.

    With ``H`` the Jacobian of ``h`` at ``mean`` and ``S = q H H^T + r I``, the
    proposal is ``N(mean + q H^T S^-1 e, (I/q + H^T H / r)^-1)``, ``e = y - h(mean)``,
    sampled by Matheron's rule ``s = mean + sqrt(q) w + q H^T S^-1 (e - H sqrt(q) w - sqrt(r) v)``.
    Its log density needs only ``n_y x n_y`` solves (``det`` by Sylvester's identity).
    """
    proposal = _GaussianProposal(_linearised(system, mean), mean, y - system.h(mean), q, r)
    sample = proposal.sample(w, v)
    return sample, proposal.log_density(sample) - gaussian_log_density(sample - mean, q)


def _draw_components(draws: np.ndarray, log_weights: np.ndarray, uniform: np.ndarray) -> np.ndarray:
    """One draw per point from a mixture: ``draws: (..., d, components)`` each component's
    draw, ``log_weights: (..., components)`` the components' normalised log weights
    (broadcasting against ``uniform``), ``uniform: (...)`` uniform numbers that pick the
    component -> ``(..., d)``."""
    chosen = (uniform[..., None] > np.cumsum(np.exp(log_weights), axis=-1)).sum(axis=-1)
    chosen = np.minimum(chosen, draws.shape[-1] - 1)
    return np.take_along_axis(draws, chosen[..., None, None], axis=-1)[..., 0]


def mixture_proposal(
    system: System,
    mean: np.ndarray,
    y: np.ndarray,
    q: float,
    components: tuple[tuple[float, float], ...],
    w: np.ndarray,
    v: np.ndarray,
    uniform: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`optimal_proposal` for a noise law that is a mixture of Gaussians,
    ``components = ((weight, variance), ...)`` (the outlier law): the optimal proposal is
    then the mixture of each component's Gaussian proposal, weighted by the weight times
    how likely the measurement is under it (exact for a linear ``h``). ``uniform: (...)``
    picks the component. Returns ``s`` and ``log q(s) - log N(s; mean, q I)``."""
    jacobian, innovation = _linearised(system, mean), y - system.h(mean)
    proposals = [_GaussianProposal(jacobian, mean, innovation, q, r) for _, r in components]
    log_weights = np.stack(
        [
            np.log(weight) + p.log_marginal()
            for (weight, _), p in zip(components, proposals, strict=True)
        ],
        axis=-1,
    )
    log_weights = log_weights - logsumexp(log_weights, axis=-1, keepdims=True)
    draws = np.stack([p.sample(w, v) for p in proposals], axis=-1)  # (..., n_x, components)
    sample = _draw_components(draws, log_weights, uniform)
    log_proposal = logsumexp(
        np.stack([p.log_density(sample) for p in proposals], axis=-1) + log_weights, axis=-1
    )
    return sample, log_proposal - gaussian_log_density(sample - mean, q)


def initial_proposal(
    mean: np.ndarray,
    covariance: np.ndarray,
    jacobian: np.ndarray,
    innovation: np.ndarray,
    components: tuple[tuple[float, float], ...],
    standard: np.ndarray,
    uniform: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray]:
    """Draw the first sample's particles from the Gaussian prior ``N(mean, covariance)``
    updated by the first measurement, whose noise is the mixture of zero-mean Gaussians
    ``components = ((weight, variance), ...)`` (one for a Gaussian law).

    With ``h`` linearised as ``jacobian: (n_y, n_x)``, the proposal is the mixture of the
    components' Kalman posteriors, each weighted by its weight times
    ``N(innovation; 0, H P H^T + r I)``: the posterior itself when ``h`` is linear. An
    outlier in the first measurement is then read with the outliers' variance instead of
    pulling every particle to it (out of the box, where all weights vanish).
    ``innovation: (batch, n_y)``, ``standard: (batch, n, n_x)`` standard normal draws,
    ``uniform: (batch, n)`` picks the component (None for one component). Returns the
    particles ``(batch, n, n_x)`` and their log proposal density up to a constant ``(batch, n)``.
    """
    n_y = jacobian.shape[0]
    posteriors = []
    for _, r in components:
        innovation_covariance = jacobian @ covariance @ jacobian.T + r * np.eye(n_y)
        gain = covariance @ jacobian.T @ np.linalg.inv(innovation_covariance)
        posterior = covariance - gain @ jacobian @ covariance
        cholesky = np.linalg.cholesky(0.5 * (posterior + posterior.T))
        posteriors.append((mean + innovation @ gain.T, cholesky, innovation_covariance))
    if len(components) == 1:
        means, cholesky, _ = posteriors[0]
        particles = means[:, None, :] + standard @ cholesky.T
        log_density = -0.5 * np.sum(standard**2, axis=-1) - np.sum(np.log(np.diag(cholesky)))
        return particles, log_density
    log_weights = np.stack(
        [
            np.log(weight) - 0.5 * _quadratic(innovation, np.linalg.cholesky(s)) - _half_log_det(s)
            for (weight, _), (_, _, s) in zip(components, posteriors, strict=True)
        ],
        axis=-1,
    )  # (batch, components)
    log_weights -= logsumexp(log_weights, axis=-1, keepdims=True)
    draws = np.stack([m[:, None, :] + standard @ c.T for m, c, _ in posteriors], axis=-1)
    particles = _draw_components(draws, log_weights[:, None, :], uniform)
    log_density = logsumexp(
        np.stack(
            [
                -0.5 * _quadratic(particles - m[:, None, :], c) - np.sum(np.log(np.diag(c)))
                for m, c, _ in posteriors
            ],
            axis=-1,
        )
        + log_weights[:, None, :],
        axis=-1,
    )
    return particles, log_density


def _quadratic(offset: np.ndarray, cholesky: np.ndarray) -> np.ndarray:
    """``offset^T (L L^T)^-1 offset`` over the last axis of ``offset: (..., d)``."""
    solved = solve_triangular(
        cholesky, np.moveaxis(offset, -1, 0).reshape(len(cholesky), -1), lower=True
    )
    return np.sum(solved**2, axis=0).reshape(offset.shape[:-1])


def _half_log_det(matrix: np.ndarray) -> float:
    """``0.5 log det`` of a symmetric positive definite matrix."""
    return 0.5 * np.linalg.slogdet(matrix)[1]
