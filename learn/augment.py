"""Density randomisation: phantom neighbours in the RBF histogram, so small-swarm policies generalise.

A policy trained with 4 robots rarely sees more than one or two neighbours, so in a swarm of 16 or
32 its RBF histogram inputs are far larger than anything it was trained on, and its behaviour
degrades (measured on localisation: final success 0.92 → 0.49 going from 4 to 32 robots; 0.95 when the histogram
is zeroed instead). During *training only*, :class:`PhantomNeighbours` adds the RBF contributions of
``Poisson(λ)`` extra neighbours per robot and step, at distances uniform over the disc between
``dist_min_mm`` and the communication radius, with one λ ~ U(0, λ_max) per env and episode. The
critic, the rewards and evaluation are untouched; the actor learns to act on histories whose
histogram ranges over the densities of larger swarms. ``λ_max = 0`` (the thesis) turns it off.
"""
from __future__ import annotations

import numpy as np

from sim.config import WorldConfig
from sim.radio import rbf_rows


class PhantomNeighbours:
    """Adds phantom neighbours to observations (B, M, obs_dim) in place; its own Generator."""

    def __init__(self, cfg: WorldConfig, lam_max: float, rng: np.random.Generator) -> None:
        assert lam_max >= 0, f"lam_max must be >= 0, got {lam_max}"
        self.cfg, self.lam_max, self.rng = cfg, float(lam_max), rng
        self.lam: np.ndarray | None = None  # (B,) phantoms per robot and step in each env

    def reset(self, n_envs: int) -> None:
        """Draw each env's density for a new episode."""
        self.lam = self.rng.uniform(0.0, self.lam_max, n_envs)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        if self.lam_max == 0:
            return obs
        assert self.lam is not None, "PhantomNeighbours used before reset"
        B, M, _ = obs.shape
        cfg = self.cfg
        k = self.rng.poisson(np.repeat(self.lam, M))  # (B*M,) phantoms per robot
        lo2, hi2 = min(cfg.dist_min_mm, cfg.comm_radius_mm) ** 2, cfg.comm_radius_mm ** 2
        d = np.sqrt(self.rng.uniform(lo2, hi2, int(k.sum())))  # (K,) uniform over the annulus' area
        if cfg.dist_integer:
            d = np.round(d)
        n = cfg.n_rbf
        slot = np.repeat(np.arange(B * M) * n, k)[:, None] + np.arange(n)  # (K, n_rbf) flat (robot, bin)
        hist = np.bincount(slot.ravel(), weights=rbf_rows(cfg, d).ravel(), minlength=B * M * n)  # sums in draw order
        obs[..., cfg.obs_slice("rbf")] += hist.reshape(B, M, n).astype(obs.dtype)
        return obs
