"""Ornstein-Uhlenbeck exploration noise (DDPG; thesis Algorithm 4), one process per robot and motor.

x ← x + θ (μ − x) + σ ε,  ε ~ N(0, 1), one step per control period (Δt = 1 step). The process
is re-initialised to μ at the start of every episode ("Initialize a random process N").
"""
from __future__ import annotations

import numpy as np


class OUNoise:
    """Temporally correlated noise of shape ``shape`` (e.g. (B, M, 2)), driven by its own Generator."""

    def __init__(self, shape: tuple[int, ...], theta: float, sigma: float, mu: float,
                 rng: np.random.Generator) -> None:
        assert theta >= 0 and sigma >= 0, f"OU needs theta, sigma >= 0, got {theta}, {sigma}"
        self.shape = tuple(shape)
        self.theta, self.sigma, self.mu = float(theta), float(sigma), float(mu)
        self.rng = rng
        self.x = np.full(self.shape, self.mu)

    def reset(self) -> None:
        """Start a new episode's process at the mean."""
        self.x = np.full(self.shape, self.mu)

    def sample(self) -> np.ndarray:
        """Advance one step and return the noise (float64, ``shape``)."""
        eps = self.rng.standard_normal(self.shape)
        self.x = self.x + self.theta * (self.mu - self.x) + self.sigma * eps
        return self.x
