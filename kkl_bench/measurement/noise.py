"""The law of the measurement noise (Gaussian, Student-t, Gaussian with outliers)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import special

from kkl_bench.protocol import SIGMA_V

NOISE_LAWS = ("gaussian", "student-t", "outliers")


@dataclass(frozen=True)
class NoiseLaw:
    """The law of each component of the measurement noise ``v_k`` (independent components).

    Attributes
    ----------
    law: ``"gaussian"``: ``sigma z``; ``"student-t"``: ``sigma t_dof`` (heavy tails; its
        variance is ``sigma^2 dof / (dof - 2)`` for ``dof > 2``); ``"outliers"``: ``sigma z``,
        times ``outlier_scale`` with probability ``outlier_fraction``.
    sigma: the scale, ``measurement_noise`` in a track file.
    dof: Student-t degrees of freedom.
    outlier_fraction, outlier_scale: the outliers' probability and size (in ``sigma``).
    """

    law: str = "gaussian"
    sigma: float = SIGMA_V
    dof: float = 3.0
    outlier_fraction: float = 0.05
    outlier_scale: float = 10.0

    def __post_init__(self) -> None:
        if self.law not in NOISE_LAWS:
            raise ValueError(f"unknown noise law {self.law!r}; valid laws: {', '.join(NOISE_LAWS)}")
        if not self.sigma >= 0:
            raise ValueError(f"noise law: sigma={self.sigma!r} must be non-negative")
        if self.law == "student-t" and not self.dof > 2:
            raise ValueError(f"student-t noise: dof={self.dof!r} must exceed 2 (finite variance)")
        if self.law == "outliers" and not (
            0 <= self.outlier_fraction < 1 and self.outlier_scale >= 1
        ):
            raise ValueError(
                f"outlier noise: outlier_fraction={self.outlier_fraction!r} must be in [0, 1) "
                f"and outlier_scale={self.outlier_scale!r} at least 1"
            )

    @property
    def gaussian(self) -> bool:
        return self.law == "gaussian"

    @property
    def variance(self) -> float:
        """The variance of each component."""
        if self.law == "student-t":
            return self.sigma**2 * self.dof / (self.dof - 2.0)
        if self.law == "outliers":
            return self.sigma**2 * (1.0 + self.outlier_fraction * (self.outlier_scale**2 - 1.0))
        return self.sigma**2

    @property
    def mixture(self) -> tuple[tuple[float, float], ...] | None:
        """``((weight, variance), ...)`` of each component when the law is a finite mixture
        of zero-mean Gaussians with more than one component (the outlier law), else None."""
        if self.law != "outliers" or self.outlier_fraction == 0:
            return None
        fraction, scale = self.outlier_fraction, self.outlier_scale
        return ((1.0 - fraction, self.sigma**2), (fraction, (scale * self.sigma) ** 2))

    def sample(self, rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
        """Noise of ``shape`` from ``rng`` (Gaussian: ``sigma * rng.standard_normal(shape)``,
        the protocol's draw, then, for the other laws, their extra draws)."""
        if self.law == "student-t":
            return self.sigma * rng.standard_t(self.dof, shape)
        noise = self.sigma * rng.standard_normal(shape)
        if self.law == "outliers":
            noise = (
                np.where(rng.random(shape) < self.outlier_fraction, self.outlier_scale, 1.0) * noise
            )
        return noise

    @property
    def student_t_log_norm(self) -> float:
        """``log`` of the Student-t law's normalizing constant at scale ``sigma``."""
        nu = self.dof
        return (
            special.gammaln((nu + 1) / 2)
            - special.gammaln(nu / 2)
            - 0.5 * math.log(nu * math.pi)
            - math.log(self.sigma)
        )

    def log_density(self, residual: np.ndarray) -> np.ndarray:
        """``log p(residual)`` summed over the last axis (``(..., n_y)`` -> ``(...)``)."""
        z = residual / self.sigma
        if self.law == "student-t":
            nu = self.dof
            each = self.student_t_log_norm - (nu + 1) / 2 * np.log1p(z**2 / nu)
        elif self.law == "outliers":
            p, s = self.outlier_fraction, self.outlier_scale
            inlier = math.log1p(-p) - 0.5 * z**2
            outlier = math.log(p) - math.log(s) - 0.5 * (z / s) ** 2 if p > 0 else -np.inf
            each = (
                np.logaddexp(inlier, outlier) - 0.5 * math.log(2 * math.pi) - math.log(self.sigma)
            )
        else:  # the particle filter's Gaussian log density since protocol v1, to the bit
            variance = self.sigma**2
            dim = residual.shape[-1]
            return -0.5 * (
                np.sum(residual**2, axis=-1) / variance + dim * np.log(2 * np.pi * variance)
            )
        return np.sum(each, axis=-1)

    def describe(self) -> str:
        if self.law == "student-t":
            return f"Student-t, {self.dof:g} dof, scale {self.sigma:g}"
        if self.law == "outliers":
            return (
                f"Gaussian {self.sigma:g}, {self.outlier_fraction:.0%} outliers "
                f"x{self.outlier_scale:g}"
            )
        return f"Gaussian {self.sigma:g}"
