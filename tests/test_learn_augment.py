"""Phantom neighbours (training-time density randomisation of the RBF histogram)."""
import numpy as np

from learn.augment import PhantomNeighbours
from sim.config import OBS_RBF, preset
from sim.events import rbf


def test_off_leaves_observations_unchanged():
    """λ_max = 0 returns the observations untouched."""
    cfg = preset("thesis")
    obs = np.random.default_rng(0).random((3, 4, cfg.obs_dim)).astype(np.float32)
    ph = PhantomNeighbours(cfg, 0.0, np.random.default_rng(1))
    ph.reset(3)
    np.testing.assert_array_equal(ph(obs.copy()), obs)


def test_adds_only_to_rbf_bins_with_the_expected_mass():
    """Only the RBF bins change, and their mean increase matches λ times the mean RBF of a uniform-in-disc distance."""
    cfg = preset("thesis")
    B, M = 200, 8
    obs = np.zeros((B, M, cfg.obs_dim), np.float32)
    ph = PhantomNeighbours(cfg, 6.0, np.random.default_rng(2))
    ph.reset(B)
    out = ph(obs.copy())
    np.testing.assert_array_equal(out[..., :OBS_RBF], 0)
    d = cfg.comm_radius_mm * np.sqrt(np.random.default_rng(3).random(200_000))
    per_phantom = rbf(cfg, d).sum(-1).mean()
    want = ph.lam.mean() * per_phantom  # E[Σ bins] per robot
    got = out[..., OBS_RBF:].sum(-1).mean()
    assert abs(got - want) < 0.05 * want, (got, want)
    assert out[..., OBS_RBF:].min() >= 0


def test_histogram_is_the_sum_of_each_robots_phantoms():
    """Each robot's added bins are exactly the sum of rbf() over its own phantoms (draws replayed)."""
    cfg = preset("kilobot")
    B, M = 3, 5
    ph = PhantomNeighbours(cfg, 4.0, np.random.default_rng(7))
    ph.reset(B)
    out = ph(np.zeros((B, M, cfg.obs_dim), np.float32))
    rng = np.random.default_rng(7)
    lam = rng.uniform(0.0, 4.0, B)
    k = rng.poisson(np.repeat(lam, M))
    d = np.round(np.sqrt(rng.uniform(cfg.dist_min_mm ** 2, cfg.comm_radius_mm ** 2, int(k.sum()))))
    ends = np.cumsum(k)
    want = np.stack([rbf(cfg, d[e - n:e]).sum(0) for n, e in zip(k, ends)]).reshape(B, M, -1)
    np.testing.assert_allclose(out[..., OBS_RBF:], want, rtol=1e-6, atol=1e-7)
    assert k.sum() > 0


def test_table_rows_are_the_computed_rbf():
    """The table lookup phantom neighbours use gives rbf_fast's bits for every integer distance, in any batch shape."""
    from sim.radio import rbf_fast, rbf_rows

    cfg = preset("kilobot")
    d = np.round(np.sqrt(np.random.default_rng(3).uniform(0.0, cfg.comm_radius_mm ** 2, 1000)))
    for x in (np.arange(256, dtype=np.float64), d, d[:7], d[:1]):
        np.testing.assert_array_equal(rbf_rows(cfg, x), rbf_fast(cfg, x))
