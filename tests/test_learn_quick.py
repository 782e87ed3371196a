"""CI smoke test of the `quick` preset, shortened: a few thousand updates already beat random search."""
import pytest

torch = pytest.importorskip("torch")

from kiloforge.policies import load_policy  # noqa: E402
from learn.config import from_preset  # noqa: E402
from learn.train import train  # noqa: E402
from sim.baselines import make_policy  # noqa: E402
from sim.env import SwarmEnv  # noqa: E402
from sim.rollout import HistoryActor, rollout  # noqa: E402


def test_quick_preset_beats_random(tmp_path):
    """2 robots, thesis world, ~32k transitions: the trained actor's final coverage clearly beats random commands."""
    cfg = from_preset("quick", world="thesis", n_robots=2, seed=1, episodes=128, max_minutes=0.0, eval_every=12_800,
                      eval_episodes=20, threads=1)
    res = train(cfg, tmp_path / "quick", progress=False, log=lambda m: None)
    assert res.counters.updates == 128 * 200 * cfg.updates_per_step
    pol = load_policy(tmp_path / "quick" / "policy_best.npz")
    env = SwarmEnv(pol.world, n_envs=40, n_robots=2, seed=0)
    learned = rollout(env, HistoryActor(pol.act, pol.t_prev, pol.world), 40, seed=99).metrics()
    rand = rollout(env, make_policy("random", pol.world), 40, seed=99).metrics()
    print(f"final coverage: trained {learned.final_coverage.mean():.3f}, random {rand.final_coverage.mean():.3f}")
    assert learned.final_coverage.mean() > max(2.5 * rand.final_coverage.mean(), rand.final_coverage.mean() + 0.1)
    assert learned.returns.mean() > 3 * max(rand.returns.mean(), 1.0)
