"""MAGRDPG (learn/magrdpg.py, learn/recurrent.py): windows, burn-in, the update, the run directory and the CLI."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from kiloforge.policies import load_policy
from kiloforge.actors.gru import GRU, GRUPolicy
from learn.cli import main_train_recurrent
from learn.config import RecurrentConfig
from learn.evaluate import LearnerPolicy
from learn.magrdpg import MAGRDPG
from learn.recurrent import GRUActor, gru_params, mlp_params
from learn.replay import EpisodeReplay
from sim.config import preset
from sim.env import SwarmEnv
from sim.rollout import rollout

WORLD = preset("thesis", episode_steps=30)


def filled_replay(T: int = 30, M: int = 2, episodes: int = 3, seed: int = 0) -> EpisodeReplay:
    """A replay holding random episodes whose tuple entries encode (episode, step) for checking."""
    rng = np.random.default_rng(seed)
    D, S = WORLD.tuple_dim, WORLD.state_dim(M)
    rep = EpisodeReplay(T * 8, T, M, D, S, 1)
    for e in range(episodes):
        first = rng.random((1, M, D)).astype(np.float32)
        first[..., 0] = 1000 * e  # marker: tuple k of episode e has x[0] = 1000 e + k
        rep.begin(first, rng.random((1, S)).astype(np.float32))
        for k in range(1, T + 1):
            x = rng.random((1, M, D)).astype(np.float32)
            x[..., 0] = 1000 * e + k
            rep.add(x, rng.random((1, S)).astype(np.float32), rng.random(1).astype(np.float32))
    return rep


def test_actor_is_pytorch_gru_and_exports_the_same_numbers():
    """GRUActor's artifact (kiloforge.actors.gru.GRUPolicy) computes the torch actor's clipped actions step by step."""
    torch.manual_seed(0)
    actor = GRUActor(WORLD.tuple_dim, 12)
    with torch.no_grad():
        actor.out.weight.mul_(200)
        actor.out.bias.fill_(0.5)
    x = torch.randn(5, 9, WORLD.tuple_dim)
    raw, h_last = actor(x, actor.initial_state(5))
    policy = GRUPolicy(**actor.arrays(), world=WORLD)
    np.testing.assert_allclose(policy.act_sequence(x.numpy()), raw.clamp(0, 1).detach().numpy(), atol=1e-5)
    cell = torch.nn.GRUCell(WORLD.tuple_dim, 12)
    g = actor.gru
    cell.load_state_dict({"weight_ih": g.weight_ih_l0, "weight_hh": g.weight_hh_l0, "bias_ih": g.bias_ih_l0,
                          "bias_hh": g.bias_hh_l0})
    h = actor.initial_state(5)
    for t in range(9):
        h = cell(x[:, t], h)
    torch.testing.assert_close(h, h_last)
    assert actor.n_params == gru_params(WORLD.tuple_dim, 12) == policy.n_params
    assert mlp_params([160, 26, 26, 2]) == 4942  # the matched MAGDDPG actor of the README comparison


def test_windows_cut_episodes_correctly():
    """Each window holds tuples k_0 .. of one episode, never before its start; transitions match the replay's."""
    rep = filled_replay()
    rng = np.random.default_rng(1)
    B, U = 5, 4
    w = rep.sample_windows(400, B, U, rng)
    assert w.x.shape == (400, 2, B + U + 1, WORLD.tuple_dim) and w.s.shape == (400, U, WORLD.state_dim(2))
    x, off = w.x.numpy(), w.off.numpy()
    ep = (x[:, 0, 0, 0] // 1000).astype(int)
    k = np.rint(x[:, 0, :, 0] - 1000 * ep[:, None]).astype(int)  # (N, L) tuple index of each position
    k0 = k[:, 0]
    ts = k0 + off
    assert np.all(k0 >= 0) and np.all((off == B) | (k0 == 0)) and np.all(off <= B)
    assert np.all(ts + U <= 30) and ts.min() == 0 and ts.max() == 30 - U
    valid = np.arange(B + U + 1)[None, :] <= (off + U)[:, None]
    np.testing.assert_array_equal(np.where(valid, k - k0[:, None], 0), np.where(valid, np.arange(B + U + 1), 0))
    e_slot = ep  # episodes were stored in slots 0, 1, 2
    ref = rep.gather(np.repeat(e_slot, U), (ts[:, None] + np.arange(U)).ravel())
    np.testing.assert_array_equal(w.s.reshape(-1, w.s.shape[-1]), ref.s)
    np.testing.assert_array_equal(w.a.reshape(-1, 2, 2), ref.a)
    np.testing.assert_array_equal(w.r.ravel(), ref.r)
    np.testing.assert_array_equal(w.s2.reshape(-1, w.s2.shape[-1]), ref.s2)


def test_burn_in_state_replays_from_the_episode_start():
    """burn_in_state equals stepping the actor over the row's first ``off`` inputs from zero; off = 0 gives zero."""
    torch.manual_seed(1)
    agent = MAGRDPG(WORLD.tuple_dim, WORLD.state_dim(2), 2, 8, (16,), 0.9, 0.1, 1e-3, 1e-3, burn_in=4)
    X = torch.randn(3, 9, WORLD.tuple_dim)
    off = torch.tensor([0, 2, 4])
    hb = agent.burn_in_state(X, off)
    for i in range(3):
        h = agent.actor.initial_state(1)
        for t in range(int(off[i])):
            _, h = agent.actor.step(X[i:i + 1, t], h)
        torch.testing.assert_close(hb[i:i + 1], h)
    assert torch.all(hb[0] == 0)


def test_update_learns_a_fixed_batch_and_moves_targets_softly():
    """Repeated updates on one batch lower the critic loss; target networks move by tau only."""
    rep = filled_replay()
    rng = np.random.default_rng(2)
    torch.manual_seed(2)
    agent = MAGRDPG(WORLD.tuple_dim, WORLD.state_dim(2), 2, 8, (32, 32), 0.5, 0.01, 1e-3, 1e-2, burn_in=3)
    w = rep.sample_windows(16, 3, 5, rng)
    before = [p.clone() for p in agent.actor_target.parameters()]
    first = agent.update(w).critic_loss
    for _ in range(30):
        last = agent.update(w).critic_loss
    assert last < 0.5 * first, (first, last)
    moved = max(float((a - b).abs().max()) for a, b in zip(agent.actor_target.parameters(), before))
    online = max(float((a.detach() - b).abs().max()) for a, b in zip(agent.actor.parameters(), before))
    assert 0 < moved < online


def test_config_validation_and_presets():
    """Bad values raise one-line ConfigErrors; presets and from_dict compose."""
    from learn.config import ConfigError
    from learn.config import RECURRENT_PRESETS as PRESETS
    assert RecurrentConfig().validate().hidden == 32
    for bad in ({"hidden": 0}, {"hidden": 300}, {"unroll": 0}, {"unroll": 500}, {"tau": 0.0}, {"world": "mars"},
                {"exp_name": "a b"}):
        with pytest.raises(ConfigError) as ei:
            RecurrentConfig.from_dict(bad).validate()
        assert "\n" not in str(ei.value)
    with pytest.raises(ConfigError, match="unknown"):
        RecurrentConfig.from_dict({"t_prev": 3})
    assert RecurrentConfig.from_dict(PRESETS["quick"]).max_minutes == 5.0
    from learn.config import CELLS
    from learn.recurrent import RECURRENT_ACTORS
    assert set(CELLS) == set(RECURRENT_ACTORS)  # every cell the config accepts has an actor


def test_cli_trains_writes_a_run_and_a_loadable_gru_policy(tmp_path, capsys):
    """A tiny run: config, metrics, curve, checkpoint, policies; the artifact acts as the torch actor did."""
    out = tmp_path / "run"
    argv = ["--robots", "2", "--out", str(out), "--quiet", "--episode-steps", "20", "--n-envs", "2",
            "--warmup-episodes", "2", "--episodes", "4", "--eval-every", "40", "--eval-episodes", "2",
            "--replay-size", "400", "--batch-windows", "4", "--unroll", "4", "--burn-in", "3", "--hidden", "6",
            "--critic-hidden", "16", "--seed", "3"]
    assert main_train_recurrent(argv) == 0
    assert "best evaluation" in capsys.readouterr().out
    for f in ("config.json", "world.json", "metrics.csv", "learning_curve.png", "checkpoint.pt",
              "policy_best.npz", "policy_last.npz", "summary.json"):
        assert (out / f).is_file(), f
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["hidden"] == 6 and cfg["unroll"] == 4
    rows = (out / "metrics.csv").read_text().splitlines()
    assert len(rows) >= 3 and rows[0].startswith("env_steps,episodes,updates")
    p = load_policy(out / "policy_last.npz")
    assert isinstance(p, GRUPolicy) and p.hidden_size == 6 and p.provenance["trainer"] == "kiloforge.learn MAGRDPG"
    assert p.provenance["updates"] > 0
    # the artifact is the actor: same evaluation episodes, same rewards
    env = SwarmEnv(p.world, 2, 2, seed=0)
    float_run = rollout(env, GRU.swarm_policy(p), 2, seed=5)
    agent = MAGRDPG(p.in_dim, p.world.state_dim(2), 2, 6, (16,), 0.9, 0.1, 1e-3, 1e-3)
    g = agent.actor.gru
    with torch.no_grad():
        for name, t in (("w_ih", g.weight_ih_l0), ("w_hh", g.weight_hh_l0), ("b_ih", g.bias_ih_l0),
                        ("b_hh", g.bias_hh_l0), ("w_out", agent.actor.out.weight), ("b_out", agent.actor.out.bias)):
            t.copy_(torch.from_numpy(np.array(getattr(p, name))))
    torch_run = rollout(env, LearnerPolicy(agent, p.world), 2, seed=5)
    np.testing.assert_allclose(float_run.rewards, torch_run.rewards, atol=1e-4)
    # resume continues, a changed field is refused
    assert main_train_recurrent(["--out", str(out), "--resume", "--quiet", "--episodes", "6"]) == 0
    assert main_train_recurrent(["--out", str(out), "--resume", "--quiet", "--hidden", "7"]) == 2
    err = capsys.readouterr().err
    assert "cannot resume with a different --hidden; only --episodes" in err
    assert "--generations" not in err  # only this trainer's knobs are offered


def test_cli_user_errors_are_one_line(tmp_path, capsys):
    """Bad options exit 2 with one line and no traceback; an existing run is not overwritten."""
    assert main_train_recurrent(["--hidden", "abc", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "hidden" in err and "Traceback" not in err
    (tmp_path / "y").mkdir()
    (tmp_path / "y" / "config.json").write_text("{}")
    assert main_train_recurrent(["--out", str(tmp_path / "y"), "--quiet"]) == 2
    assert "already holds a run" in capsys.readouterr().err
    assert main_train_recurrent(["--resume", "--quiet"]) == 2


@pytest.mark.slow
def test_learns_the_two_robot_task(tmp_path):
    """Ten minutes of MAGRDPG on 2 robots (thesis world) clearly beat the random baseline's return."""
    out = tmp_path / "gru2"
    assert main_train_recurrent(["--robots", "2", "--out", str(out), "--quiet", "--max-minutes", "10"]) == 0
    best = max(float(r.split(",")[4]) for r in (out / "metrics.csv").read_text().splitlines()[1:])
    assert best > 300.0, best


@pytest.mark.parametrize("cell", ["gru", "lstm"])
def test_one_loop_resumes_recurrent_runs_exactly(tmp_path, cell):
    """learn.train.train runs MAGRDPG (GRU and LSTM): stopping after 2 learning episodes and resuming to 4
    equals one run; the artifact is of the cell's kind."""
    from learn.checkpoint import load_checkpoint
    from learn.train import train
    tiny = dict(world="thesis", n_robots=2, episode_steps=20, n_envs=2, warmup_episodes=2, episodes=4, eval_every=40, eval_episodes=2,
                replay_size=400, batch_windows=4, unroll=4, burn_in=3, hidden=6, critic_hidden=(16,), seed=4, cell=cell)
    quiet = lambda m: None  # noqa: E731
    full = train(RecurrentConfig(**tiny), tmp_path / "full", progress=False, log=quiet)
    train(RecurrentConfig(**{**tiny, "episodes": 2}), tmp_path / "split", progress=False, log=quiet)
    resumed = train(RecurrentConfig(**tiny), tmp_path / "split", resume=True, progress=False, log=quiet)
    assert resumed.counters.updates == full.counters.updates > 0
    a, b = load_checkpoint(tmp_path / "full"), load_checkpoint(tmp_path / "split")
    for part in ("actor", "critic", "actor_target", "critic_target"):
        for k in a["agent"][part]:
            torch.testing.assert_close(a["agent"][part][k], b["agent"][part][k], rtol=0, atol=0)
    np.testing.assert_array_equal(a["replay"][0]["tuples"], b["replay"][0]["tuples"])
    assert a["rng"]["replay"] == b["rng"]["replay"] and a["rng"]["noise"] == b["rng"]["noise"]
    assert load_policy(tmp_path / "split" / "policy_last.npz").kind == cell
