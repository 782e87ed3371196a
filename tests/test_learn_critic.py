"""The mean-embedding critic (order and count invariant), training across swarm sizes, and the learning rewards."""
import dataclasses

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from learn.config import ConfigError, TrainConfig  # noqa: E402
from learn.groups import size_shares  # noqa: E402
from learn.networks import ROBOT_FEATURES, MeanCritic  # noqa: E402
from learn.rewards import LearningReward, potential  # noqa: E402
from learn.train import train  # noqa: E402
from sim.config import preset  # noqa: E402
from sim.env import SwarmEnv  # noqa: E402


def _state_action(N: int, M: int, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    s = torch.rand(N, 2 + 3 * M, generator=gen) * 2 - 1
    return s, torch.rand(N, M, 2, generator=gen), torch.rand(N, M, 5, generator=gen)


@pytest.mark.parametrize("pool, obs_dim", [("mean", 0), ("meanmax", 5)])
def test_mean_critic_is_invariant_to_robot_order(pool, obs_dim):
    """Permuting the robots (their state blocks, actions and observations together) leaves Q unchanged."""
    torch.manual_seed(0)
    critic = MeanCritic((16, 16), (32, 16), pool, obs_dim)
    with torch.no_grad():
        critic.head[-1].weight.mul_(1000.0)  # make Q vary visibly (the thesis init keeps it near 0)
    gen = torch.Generator().manual_seed(1)
    N, M = 6, 7
    s, a, o = _state_action(N, M, gen)
    o = o if obs_dim else None
    perm = torch.randperm(M, generator=gen)
    robots = s[:, 2:].reshape(N, M, 3)[:, perm].reshape(N, 3 * M)
    s_p = torch.cat([s[:, :2], robots], dim=1)
    q, q_p = critic(s, a, o), critic(s_p, a[:, perm], None if o is None else o[:, perm])
    assert q.std() > 1e-3  # not a constant
    torch.testing.assert_close(q_p, q, rtol=1e-5, atol=1e-6)
    swap = torch.cat([s[:, :2], s[:, 2:].reshape(N, M, 3)[:, [1, 0] + list(range(2, M))].reshape(N, 3 * M)], 1)
    assert not torch.allclose(critic(swap, a, o), q)  # robots are not interchangeable without their actions


def test_one_set_of_weights_runs_at_4_and_32_robots():
    """The same MeanCritic evaluates 4- and 32-robot states; its per-robot features have the documented width."""
    torch.manual_seed(2)
    critic = MeanCritic((16,), (16,))
    gen = torch.Generator().manual_seed(3)
    for M in (4, 32):
        s, a, _ = _state_action(5, M, gen)
        q = critic(s, a)
        assert q.shape == (5,) and torch.isfinite(q).all()
        assert critic.features(s, a).shape == (5, M, ROBOT_FEATURES)
        (g,) = torch.autograd.grad(critic(s, a.requires_grad_(True)).sum(), a)
        assert g.shape == (5, M, 2)  # ∇_a Q for every robot: what the actor step needs
    with pytest.raises(AssertionError, match="does not match"):
        critic(torch.zeros(2, 2 + 3 * 4), torch.zeros(2, 5, 2))


def test_size_shares_split_a_minibatch():
    """Shares add up, give every size a sample, and follow the documented proportions."""
    assert size_shares(256, (4,), "equal") == [256]
    assert size_shares(256, (4, 16, 32), "equal") == [86, 85, 85]
    assert size_shares(256, (4, 16, 32), "robots") == [20, 79, 157]
    assert size_shares(3, (1, 100, 1000), "robots") == [1, 1, 1]
    assert size_shares(0, (4, 16), "equal") == [0, 0]


def test_several_swarm_sizes_train_one_actor_and_one_critic(tmp_path):
    """--robots 2 5 --critic mean: one run, a replay per size, eval columns per size; concat refuses several sizes."""
    with pytest.raises(ConfigError, match="critic mean"):
        TrainConfig(n_robots=(2, 5)).validate()
    cfg = TrainConfig(world="thesis", n_robots=(2, 5), critic="mean", critic_embed=(8,), critic_hidden=(16,), t_prev=3,
                      episode_steps=20, actor_hidden=(8,), n_envs=2, warmup_episodes=4, episodes=8, batch_size=8,
                      replay_size=400, updates_per_step=0.5, eval_every=80, eval_episodes=2, actor_robots=2, seed=1)
    res = train(cfg, tmp_path / "mix", progress=False, log=lambda m: None)
    row = res.counters.rows[-1]
    assert row["env_steps"] == 3 * 2 * 2 * 20 and res.counters.updates > 0  # 3 batches x 2 envs x 2 sizes
    for M in (2, 5):
        assert 0.0 <= row[f"eval_final_coverage_m{M}"] <= 1.0
    assert row["eval_return"] == pytest.approx((row["eval_return_m2"] + row["eval_return_m5"]) / 2)
    from kiloforge.policies import load_policy
    p = load_policy(tmp_path / "mix" / "policy_last.npz")
    assert p.provenance["trained_robots"] == [2, 5] and p.provenance["config"]["n_robots"] == [2, 5]
    assert train(cfg, tmp_path / "mix", resume=True, progress=False, log=lambda m: None).counters.updates == \
        res.counters.updates  # resumes (nothing left to do)


def test_learning_rewards():
    """linear = team + scale (c - c²); potential = team + w scale (γ Φ(s') - Φ(s)), Φ the in-range closeness."""
    world = preset("thesis")
    env = SwarmEnv(world, 3, 4, seed=0)
    env.reset(seed=1)
    phi0 = potential(env)
    d = np.linalg.norm(env.pos - env.target[:, None], axis=-1)
    np.testing.assert_allclose(phi0, np.mean(np.clip(1 - d / world.comm_radius_mm, 0, None), axis=1))
    shaped, linear = LearningReward("potential", world, 0.9, 2.0), LearningReward("linear", world, 0.9)
    shaped.reset(env)
    a = np.full((3, 4, 2), 0.5)
    _, r, _, _, info = env.step(a)
    phi1 = potential(env)
    np.testing.assert_allclose(shaped(env, r, info, a), r + 2.0 * world.reward_scale * (0.9 * phi1 - phi0), rtol=1e-6)
    c = info["coverage"]
    np.testing.assert_allclose(linear(env, r, info, a), r + world.reward_scale * (c - c * c), rtol=1e-6)
    extra = LearningReward("team", world, 0.9, extra_action_penalty=0.1)
    np.testing.assert_allclose(extra(env, r, info, a), r - world.reward_scale * 0.1 * 0.5, rtol=1e-6)


def test_randomise_reaches_training_envs_only(tmp_path, monkeypatch):
    """randomise=NAME passes sim.variants.RANDOMISATIONS[NAME] to the training envs, not to the evaluation envs
    (unless randomise_eval); an unknown name is a one-line ConfigError."""
    import sys
    import types

    import learn.groups as groups
    from sim.variants import RANDOMISATIONS
    assert groups.randomisation("table") is RANDOMISATIONS["table"]  # the simulator's own named randomisations
    marker = object()
    monkeypatch.setitem(sys.modules, "sim.variants", types.SimpleNamespace(RANDOMISATIONS={"test": marker}))
    seen = []

    class Recording(SwarmEnv):
        def __init__(self, *args, randomise=None, **kw):
            seen.append(randomise)
            super().__init__(*args, **kw)

    monkeypatch.setattr(groups, "SwarmEnv", Recording)
    with pytest.raises(ConfigError, match="unknown randomise 'wide'"):
        TrainConfig(randomise="wide").validate()
    base = dict(world="thesis", n_robots=2, t_prev=2, episode_steps=10, actor_hidden=(4,), critic_hidden=(8,), n_envs=2,
                warmup_episodes=2, episodes=0, batch_size=4, replay_size=200, eval_episodes=2, randomise="test")
    train(TrainConfig(**base), tmp_path / "a", progress=False, log=lambda m: None)
    assert seen == [marker, None]  # the training group, then the evaluator
    seen.clear()
    train(TrainConfig(**base, randomise_eval=True), tmp_path / "b", progress=False, log=lambda m: None)
    assert seen == [marker, marker]


def test_per_robot_critic_gives_each_robot_its_own_value():
    """critic robot: Q is (N, M), follows a permutation of the robots, and a robot's own action moves its value most."""
    torch.manual_seed(0)
    critic = MeanCritic((16, 16), (32, 16), per_robot=True)
    with torch.no_grad():
        critic.head[-1].weight.mul_(1000.0)
    gen = torch.Generator().manual_seed(1)
    N, M = 6, 7
    s, a, _ = _state_action(N, M, gen)
    q = critic(s, a)
    assert q.shape == (N, M) and q.std() > 1e-3
    perm = torch.randperm(M, generator=gen)
    s_p = torch.cat([s[:, :2], s[:, 2:].reshape(N, M, 3)[:, perm].reshape(N, 3 * M)], dim=1)
    torch.testing.assert_close(critic(s_p, a[:, perm]), q[:, perm], rtol=1e-5, atol=1e-6)
    jac = torch.autograd.functional.jacobian(lambda x: critic(s[:1], x)[0], a[:1])  # (M, 1, M, 2): ∂Q_i/∂a_j
    own = jac[torch.arange(M), 0, torch.arange(M)].abs().sum(-1)  # (M,)
    cross = jac[:, 0].abs().sum(-1).sum(1) - own  # (M,) summed over the M - 1 others
    assert torch.all(own > cross / (M - 1))  # the own action's direct path is stronger than any other robot's on average


def test_local_reward_pays_each_robot_its_own_success():
    """reward local: (B, M) scale (in range_i - penalty ||a_i||²), whose robot mean is the linear reward; it needs critic robot."""
    world = preset("kilobot")
    env = SwarmEnv(world, 3, 5, seed=0)
    env.reset(seed=2)
    a = np.random.default_rng(0).uniform(0, 1, (3, 5, 2))
    _, r, _, _, info = env.step(a)
    local, linear = LearningReward("local", world, 0.9), LearningReward("linear", world, 0.9)
    r_i = local(env, r, info, a)
    assert r_i.shape == (3, 5) and r_i.dtype == np.float32
    u = np.floor(a * 255 + 0.5) / 255  # the kilobot world executes uint8 commands
    expect = world.reward_scale * (info["in_range"] - world.action_penalty * np.sum(u * u, axis=-1))
    np.testing.assert_allclose(r_i, expect, rtol=1e-6)
    np.testing.assert_allclose(r_i.mean(axis=1), linear(env, r, info, a), rtol=1e-5, atol=1e-6)
    with pytest.raises(ConfigError, match="critic robot"):
        TrainConfig(reward="local", critic="mean").validate()
    with pytest.raises(ConfigError, match="demo-policy none"):
        TrainConfig(reward="local", critic="robot", demo_policy="searcher").validate()


def test_local_reward_trains_and_resumes(tmp_path):
    """--reward local --critic robot: the replay holds (N, M) rewards, updates run, and a resumed run equals the whole one."""
    cfg = TrainConfig(world="thesis", n_robots=(3,), critic="robot", reward="local", critic_embed=(8,), critic_hidden=(16,),
                      t_prev=2, episode_steps=20, actor_hidden=(8,), n_envs=2, warmup_episodes=2, episodes=6, batch_size=8,
                      replay_size=400, updates_per_step=0.5, eval_every=40, eval_episodes=2, checkpoint_every=1, seed=3)
    whole = train(cfg, tmp_path / "whole", progress=False, log=lambda m: None)
    assert whole.counters.updates > 0 and np.isfinite(whole.counters.rows[-1]["critic_loss"])
    half = dataclasses.replace(cfg, episodes=4)
    train(half, tmp_path / "part", progress=False, log=lambda m: None)
    resumed = train(cfg, tmp_path / "part", resume=True, progress=False, log=lambda m: None)
    from kiloforge.policies import load_policy
    w1, w2 = load_policy(tmp_path / "whole" / "policy_last.npz"), load_policy(tmp_path / "part" / "policy_last.npz")
    for x, y in zip(w1.weights, w2.weights):
        np.testing.assert_array_equal(x, y)
    assert resumed.counters.updates == whole.counters.updates
