"""Guided MAGRDPG (learn/demos.py): the demonstrator, demo episodes, behaviour cloning, the Q-filter, the CLI."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from kiloforge.policies import load_policy
from kiloforge.actors.gru import GRUPolicy
from learn.cli import main_train_recurrent
from learn.config import RecurrentConfig
from learn.demos import bc_pretrain, collect_demos, demonstrator
from learn.magrdpg import MAGRDPG
from learn.replay import concat
from sim.baselines import HandWrittenSearcher, SearcherParams
from sim.config import OBS_RBF, OBS_TARGET, preset
from sim.env import SwarmEnv
from sim.rollout import rollout

WORLD = preset("thesis", episode_steps=30)


def test_turn_sign_fixes_the_turn_direction_and_keeps_the_random_stream():
    """turn_sign=+1 never commands a right turn; both variants draw the same random numbers."""
    world = preset("thesis")
    env = SwarmEnv(world, 8, 3, seed=4)
    left = rollout(env, HandWrittenSearcher(world, SearcherParams(turn_sign=1)), 8, seed=9, record=True)
    a = left.trajectories.actions.reshape(-1, 2)
    assert np.any((a[:, 0] == 1) & (a[:, 1] == 0)), "no left turn at all"
    assert not np.any((a[:, 0] == 0) & (a[:, 1] == 1)), "a right turn with turn_sign=+1"
    rng_a, rng_b = np.random.default_rng(1), np.random.default_rng(1)
    obs = SwarmEnv(world, 2, 3, seed=0).reset()[0]
    p, q = HandWrittenSearcher(world, SearcherParams(turn_sign=1)), HandWrittenSearcher(world)
    p.reset(2, 3, rng_a)
    q.reset(2, 3, rng_b)
    p.act(obs), q.act(obs)
    assert rng_a.random() == rng_b.random()
    with pytest.raises(ValueError, match="turn_sign"):
        SearcherParams(turn_sign=3)


def test_demo_episodes_are_the_demonstrators_rollouts():
    """collect_demos stores [a_{t-1}, o_t] tuples, states and rewards exactly as the demonstrator ran them."""
    rep = collect_demos(WORLD, 2, 5, 4, np.random.default_rng(0))
    assert rep.n_slots == 8 and int((rep.filled == WORLD.episode_steps).sum()) == 8  # rounded up to 2 batches of 4
    x = rep.tuples[:8].numpy().transpose(0, 2, 1, 3)  # (E, T + 1, M, D)
    assert np.all(x[:, 0, :, :2] == 0)  # a_0 = 0
    assert set(np.unique(x[:, 1:, :, :2])) <= {0.0, 1.0}  # the searcher's commands: stop, turn, straight
    assert np.all(np.isfinite(x)) and np.all(np.isfinite(rep.states[:8].numpy()))
    assert np.all(np.isfinite(rep.rewards[:8].numpy()))
    # the stored rewards are what the env paid: replay the first batch's actions in a fresh env
    rng = np.random.default_rng(0)  # collect_demos draws the env seed, then each batch's reset seed
    env = SwarmEnv(WORLD, 4, 2, seed=int(rng.integers(2 ** 31)))
    obs, _ = env.reset(seed=int(rng.integers(2 ** 31)))
    np.testing.assert_array_equal(obs.astype(np.float32), x[:4, 0, :, 2:])
    rewards = []
    for t in range(WORLD.episode_steps):
        obs, r, *_ = env.step(x[:4, t + 1, :, :2].astype(np.float64))
        rewards.append(r)
    np.testing.assert_array_equal(np.stack(rewards, 1), rep.rewards[:4].numpy())
    np.testing.assert_array_equal(obs.astype(np.float32)[..., OBS_RBF:], x[:4, -1, :, 2 + OBS_RBF:])


def test_demonstrator_searches_as_well_as_the_hand_written_searcher():
    """The left-turning demonstrator finds the target in every episode and covers it (thesis world, 2 robots)."""
    world = preset("thesis")
    m = rollout(SwarmEnv(world, 20, 2, seed=0), demonstrator(world), 20, seed=3).metrics().summary()
    assert m["found_rate"].mean == 1.0 and m["final_coverage"].mean > 0.85


def test_demo_stop_dist_moves_where_the_demonstrator_stops():
    """demo_stop_dist replaces the tuned stopping distance (0 keeps it): stopping at 0.94 of the range leaves the
    robots farther from the beacon than the tuned 0.6 does; out-of-range values are a one-line ConfigError."""
    from learn.config import ConfigError, ESConfig
    from sim.baselines import TUNED
    world = preset("kilobot", episode_steps=150)
    assert demonstrator(world).p.stop_dist == TUNED["kilobot"].stop_dist == 0.6
    assert demonstrator(world, 0.94).p.stop_dist == 0.94
    mean_dist = {}
    for sd in (0.0, 0.94):
        env = SwarmEnv(world, 8, 4, seed=5)
        pol = demonstrator(world, sd)
        obs, _ = env.reset(seed=5)
        pol.reset(8, 4, np.random.default_rng(5))
        for _ in range(150):
            obs, *_ = env.step(pol.act(obs))
        mean_dist[sd] = float(np.linalg.norm(env.pos - env.target[:, None], axis=-1).mean())
    assert mean_dist[0.94] > mean_dist[0.0] + 5.0, mean_dist
    with pytest.raises(ConfigError, match="demo_stop_dist must be in"):
        ESConfig(demo_stop_dist=1.5).validate()


def test_pusher_demonstrator_is_the_pusher_with_imitable_turns():
    """--demo-policy pusher: sim.baselines.PUSHER on the tuned searcher, turns fixed (left; alternating at the target),
    accepted by both trainers' configs; collect_demos plays it (no right turn away from the target's range)."""
    from learn.config import ESConfig, TrainConfig
    from sim.baselines import PUSHER, TUNED
    world = preset("kilobot", episode_steps=60)
    assert demonstrator(world, kind="pusher").p == dataclasses.replace(TUNED["kilobot"], **PUSHER, turn_sign=2)
    ESConfig(demo_policy="pusher").validate()
    TrainConfig(world="kilobot", demo_policy="pusher").validate()
    rep = collect_demos(world, 4, 4, 4, np.random.default_rng(0), kind="pusher", t_prev=1)
    x = rep.tuples[:4].numpy().transpose(0, 2, 1, 3)  # (episodes, T + 1, robots, [a_{t-1}, o_t])
    a, heard = x[:, 1:, :, :2], x[:, :-1, :, 2 + OBS_TARGET] >= 0
    right = (a[..., 0] == 0) & (a[..., 1] == 1)
    assert (a.sum(-1) > 0).any() and not (right & ~heard).any()


def test_behaviour_cloning_fits_the_demonstrations():
    """bc_pretrain lowers the squared error of the GRU's commands on the demo episodes (unrolled from zero)."""
    rep = collect_demos(WORLD, 2, 8, 8, np.random.default_rng(1))
    torch.manual_seed(0)
    agent = MAGRDPG(WORLD.tuple_dim, WORLD.state_dim(2), 2, 16, (16,), 0.9, 0.1, 1e-3, 1e-3)

    def mse() -> float:
        with torch.no_grad():
            return float(agent.bc_loss(rep, 64, np.random.default_rng(5)))

    before = mse()
    bc_pretrain(agent, [rep], [8], 150, 3e-3, np.random.default_rng(0))
    assert mse() < 0.5 * before, (before, mse())


class StepCritic(torch.nn.Module):
    """Q(s, a) = 1 when the joint command sum exceeds 0.5, else 0: flat (∇_a Q = 0), so only BC can move the actor."""

    def __init__(self) -> None:
        super().__init__()
        self.b = torch.nn.Parameter(torch.zeros(()))  # lets the critic step run

    def forward(self, s: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        return (a.sum(dim=(1, 2)) > 0.5).to(a.dtype) + 0.0 * a.sum(dim=(1, 2)) + 0.0 * self.b


def test_q_filtered_bc_pulls_the_actor_towards_demonstrations_where_the_critic_prefers_them():
    """The Q-filter passes exactly the demo steps the critic rates higher; there BC moves the actor towards the
    demo commands; critic-only updates (train_actor=False) leave the actor untouched."""
    import copy
    rep = collect_demos(WORLD, 2, 8, 8, np.random.default_rng(2))
    rng = np.random.default_rng(3)
    torch.manual_seed(3)
    agent = MAGRDPG(WORLD.tuple_dim, WORLD.state_dim(2), 2, 8, (32,), 0.5, 0.01, 1e-2, 1e-3, burn_in=3)
    w = concat(rep.sample_windows(4, 3, 5, rng), rep.sample_windows(4, 3, 5, rng))
    assert w.x.shape[0] == 8 and w.s.shape[:2] == (8, 5)
    actor0 = [p.detach().clone() for p in agent.actor.parameters()]
    st = agent.update(w, n_demo=4, bc_weight=1.0, train_actor=False)
    assert np.isnan(st.bc_pass)
    assert all(torch.equal(a, b) for a, b in zip(agent.actor.parameters(), actor0))

    agent.critic, agent.critic_target = StepCritic(), StepCritic()
    plain, guided = copy.deepcopy(agent), copy.deepcopy(agent)
    # the actor's own commands on the demo steps (rows n*U + t of the last 4 windows), before the update
    X = w.x[4:].reshape(8, -1, WORLD.tuple_dim)  # (windows x robots, L, D), layout of learn.replay.Windows
    off = w.off[4:].repeat_interleave(2)
    pos = off[:, None] + torch.arange(5)
    with torch.no_grad():
        a_own, _ = agent.actor(X[torch.arange(8)[:, None], pos], agent.burn_in_state(X, off))  # (8, 5, 2)
    own = a_own.reshape(4, 2, 5, 2).permute(0, 2, 1, 3).reshape(20, 2, 2).sum(dim=(1, 2))
    demo = w.a[4:].reshape(20, 2, 2).sum(dim=(1, 2))
    prefer = (demo > 0.5) & (own <= 0.5)  # Q(demo) = 1 > Q(own) = 0
    expected_pass = float(prefer.float().mean())
    assert 0.0 < expected_pass, "the test needs demo steps that the critic prefers"
    plain.update(w, n_demo=4, bc_weight=0.0)
    st = guided.update(w, n_demo=4, bc_weight=100.0)
    assert st.bc_pass == pytest.approx(expected_pass)

    def demo_error(ag: MAGRDPG) -> float:
        with torch.no_grad():
            a, _ = ag.actor(X[torch.arange(8)[:, None], pos], ag.burn_in_state(X, off))
        a = a.reshape(4, 2, 5, 2).permute(0, 2, 1, 3).reshape(20, 2, 2)
        return float(((a - w.a[4:].reshape(20, 2, 2)) ** 2)[prefer].mean())

    assert all(torch.equal(a, b) for a, b in zip(plain.actor.parameters(), actor0))  # flat critic: no step
    assert demo_error(guided) < demo_error(plain)


def test_guided_config_validation():
    """Bad guidance values raise one-line ConfigErrors; the guided preset enables the demonstrator."""
    from learn.config import ConfigError
    from learn.config import RECURRENT_PRESETS as PRESETS
    for bad in ({"demo_policy": "oracle"}, {"demo_episodes": 0}, {"bc_weight": -1.0}, {"bc_lr": 0.0},
                {"actor_delay": -1}, {"critic_pretrain": -5}, {"action_gradient": "tanh"}):
        with pytest.raises(ConfigError) as ei:
            RecurrentConfig.from_dict(bad).validate()
        assert "\n" not in str(ei.value)
    g = RecurrentConfig.from_dict(PRESETS["guided"]).validate()
    assert g.demo_policy == "searcher" and g.bc_updates > 0 and g.actor_delay > 0 and g.action_gradient == "clip"


def test_guided_cli_clones_then_learns_and_keeps_the_cloned_actor(tmp_path, capsys):
    """A tiny guided run writes demos.json and policy_bc.npz, evaluates the cloned actor, and resumes."""
    out = tmp_path / "run"
    argv = ["--preset", "guided", "--robots", "2", "--out", str(out), "--quiet", "--episode-steps", "20",
            "--n-envs", "2", "--demo-episodes", "4", "--bc-updates", "30", "--critic-pretrain", "3", "--actor-delay", "5",
            "--warmup-episodes", "2", "--episodes", "4", "--eval-every", "40", "--eval-episodes", "2",
            "--replay-size", "400", "--batch-windows", "4", "--demo-windows", "2", "--unroll", "4", "--burn-in", "3",
            "--hidden", "6", "--critic-hidden", "16", "--seed", "3"]
    assert main_train_recurrent(argv) == 0
    log = capsys.readouterr().out
    assert "behaviour cloning: loss" in log and "demonstrations: 4 episodes" in log
    assert "critic pre-training: 3 updates" in log
    info = json.loads((out / "demos.json").read_text())
    assert info["demo_episodes"] == 4 and info["bc_updates"] == 30
    assert 0.0 <= info["eval_after_bc"]["eval_final_coverage"] <= 1.0
    p = load_policy(out / "policy_bc.npz")
    assert isinstance(p, GRUPolicy) and p.hidden_size == 6
    header = (out / "metrics.csv").read_text().splitlines()[0]
    assert header.endswith(",bc_pass")
    assert main_train_recurrent(["--out", str(out), "--resume", "--quiet", "--episodes", "6"]) == 0


@pytest.mark.slow
def test_guided_run_reaches_the_hand_written_searcher(tmp_path):
    """A short guided run (2 robots, thesis world): its best GRU matches the hand-written searcher on fresh episodes."""
    from kiloforge.policies import swarm_policy
    from sim.baselines import make_policy
    out = tmp_path / "guided"
    assert main_train_recurrent(["--preset", "guided", "--robots", "2", "--out", str(out), "--quiet",
                                 "--max-minutes", "3"]) == 0
    p = load_policy(out / "policy_best.npz")
    env = SwarmEnv(p.world, 50, 2, seed=777)
    gru = rollout(env, swarm_policy(p), 100, seed=777).metrics().summary()["final_coverage"]
    hw = rollout(env, make_policy("baseline", p.world), 100, seed=777).metrics().summary()["final_coverage"]
    assert gru.mean >= hw.mean - hw.ci95, (gru, hw)


def test_metrics_csv_keeps_extra_columns_of_later_rows():
    """rows_to_csv writes MAGRDPG's bc_pass even when only later rows have it (a run resumed from before it)."""
    from learn.train import METRIC_COLUMNS, rows_to_csv
    old = {k: 1.0 for k in METRIC_COLUMNS}
    text = rows_to_csv([old, {**old, "bc_pass": 0.5}])
    header, first, second = text.splitlines()
    assert header.endswith(",bc_pass") and first.endswith(",") and second.endswith(",0.5")


class LessIsBetterCritic(torch.nn.Module):
    """Q(s, a) = -Σ a: every command wants to go down."""

    def __init__(self) -> None:
        super().__init__()
        self.b = torch.nn.Parameter(torch.zeros(()))

    def forward(self, s: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        return -a.sum(dim=(1, 2)) + 0.0 * self.b


def test_clip_action_gradient_leaves_saturated_commands_alone():
    """action_gradient='clip': commands beyond a bound get no gradient; 'invert' pushes them back inside."""
    rep = collect_demos(WORLD, 2, 4, 4, np.random.default_rng(4))
    w = rep.sample_windows(4, 3, 5, np.random.default_rng(5))
    out = {}
    for mode in ("clip", "invert"):
        torch.manual_seed(6)
        agent = MAGRDPG(WORLD.tuple_dim, WORLD.state_dim(2), 2, 8, (16,), 0.5, 0.01, 1e-2, 1e-3, burn_in=3,
                        action_gradient=mode)
        with torch.no_grad():
            agent.actor.out.weight.zero_()
            agent.actor.out.bias.fill_(1.5)  # every raw command at 1.5: beyond the upper bound
        agent.critic, agent.critic_target = LessIsBetterCritic(), LessIsBetterCritic()
        before = [p.detach().clone() for p in agent.actor.parameters()]
        agent.update(w)
        out[mode] = max(float((p.detach() - b).abs().max()) for p, b in zip(agent.actor.parameters(), before))
    assert out["clip"] == 0.0 and out["invert"] > 0.0, out
    with pytest.raises(AssertionError, match="action_gradient"):
        MAGRDPG(WORLD.tuple_dim, WORLD.state_dim(2), 2, 8, (16,), 0.5, 0.01, 1e-2, 1e-3, action_gradient="tanh")


def test_guided_mlp_cloning_reaches_the_demonstrator(tmp_path):
    """MLP behaviour cloning on T_prev histories (as the firmware builds them): on fresh episodes the clone
    (policy_bc.npz, run by sim's HistoryActor) reaches 90 % of the left-turning searcher's final coverage."""
    from kiloforge.policies import swarm_policy
    from learn.config import TrainConfig
    from learn.train import train
    from sim.baselines import make_policy
    cfg = TrainConfig(world="thesis", n_robots=2, t_prev=10, episode_steps=100, n_envs=16, demo_policy="searcher", demo_episodes=64,
                      bc_updates=300, warmup_episodes=0, episodes=0, batch_size=256, replay_size=1600,
                      eval_episodes=10, seed=1)
    train(cfg, tmp_path / "bc", progress=False, log=lambda m: None)
    p = load_policy(tmp_path / "bc" / "policy_bc.npz")
    assert p.kind == "mlp" and p.t_prev == 10 and p.hidden == [32, 32]
    env = SwarmEnv(p.world, 50, 2, seed=777)
    cover = {name: rollout(env, pol, 100, seed=777).metrics().final_coverage.mean()
             for name, pol in (("clone", swarm_policy(p)), ("demonstrator", demonstrator(p.world)),
                               ("random", make_policy("random", p.world)))}
    assert cover["clone"] >= 0.9 * cover["demonstrator"] and cover["clone"] > 3 * cover["random"], cover
    info = json.loads((tmp_path / "bc" / "demos.json").read_text())
    assert info["eval_after_bc"]["eval_final_coverage"] > 0.5


def test_guided_mlp_cli_clones_learns_and_resumes(tmp_path, capsys):
    """`learn train --preset guided`: demonstrations, cloning, critic pre-training, Q-filtered RL, resume."""
    from learn.__main__ import main
    out = tmp_path / "run"
    argv = ["train", "--world", "thesis", "--preset", "guided", "--robots", "2", "--history", "3", "--out", str(out), "--quiet",
            "--episode-steps", "20", "--n-envs", "2", "--demo-episodes", "4", "--bc-updates", "20",
            "--critic-pretrain", "3", "--actor-delay", "5", "--warmup-episodes", "2", "--episodes", "4",
            "--eval-every", "40", "--eval-episodes", "2", "--replay-size", "400", "--batch-size", "8",
            "--demo-transitions", "4", "--actor-hidden", "8", "--critic-hidden", "16", "--seed", "3"]
    assert main(argv) == 0
    log = capsys.readouterr().out
    assert "behaviour cloning: loss" in log and "critic pre-training: 3 updates" in log
    assert load_policy(out / "policy_bc.npz").kind == "mlp"
    header = (out / "metrics.csv").read_text().splitlines()[0]
    assert header.endswith(",bc_pass")
    assert main(["train", "--out", str(out), "--resume", "--quiet", "--episodes", "6"]) == 0
    assert "resumed" in capsys.readouterr().out
