"""Training loop: determinism, exact resume, config validation, CLI (train / plot / evaluate) smoke tests."""
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from kiloforge.policies import load_policy  # noqa: E402
from learn.__main__ import main  # noqa: E402
from learn.checkpoint import load_checkpoint  # noqa: E402
from learn.config import ConfigError, TrainConfig, from_preset  # noqa: E402
from learn.train import read_metrics, train  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]

#: a run of a few seconds: 20-step episodes, tiny networks
TINY = dict(world="thesis", n_robots=2, t_prev=3, episode_steps=20, actor_hidden=(8,), critic_hidden=(16, 16), n_envs=2,
            warmup_episodes=2, episodes=4, batch_size=8, replay_size=400, updates_per_step=0.5,
            eval_every=40, eval_episodes=2, threads=1, tau=0.05)

TINY_ARGS = ["--world", "thesis", "--robots", "2", "--history", "3", "--episode-steps", "20", "--actor-hidden", "8",
             "--critic-hidden", "16", "16", "--n-envs", "2", "--warmup-episodes", "2", "--episodes", "4",
             "--batch-size", "8", "--replay-size", "400", "--updates-per-step", "0.5", "--eval-every", "40",
             "--eval-episodes", "2", "--threads", "1", "--quiet"]


def _weights(run_dir: Path) -> dict:
    return load_checkpoint(run_dir / "checkpoint.pt")["agent"]


def _assert_same_agent(a: dict, b: dict) -> None:
    for part in ("actor", "critic", "actor_target", "critic_target"):
        for k in a[part]:
            torch.testing.assert_close(a[part][k], b[part][k], rtol=0, atol=0)


def _quiet(_msg: str) -> None:
    pass


def test_same_seed_same_run(tmp_path):
    """Two runs with one seed give identical networks and evaluations; another seed differs."""
    cfg = TrainConfig(**TINY, seed=3)
    r1 = train(cfg, tmp_path / "a", progress=False, log=_quiet)
    r2 = train(cfg, tmp_path / "b", progress=False, log=_quiet)
    r3 = train(TrainConfig(**TINY, seed=4), tmp_path / "c", progress=False, log=_quiet)
    _assert_same_agent(_weights(r1.run_dir), _weights(r2.run_dir))
    assert r1.counters.updates == r2.counters.updates > 0
    cols = ("env_steps", "updates", "eval_return", "train_return", "critic_loss")
    np.testing.assert_array_equal([[r[c] for c in cols] for r in r1.counters.rows],
                                  [[r[c] for c in cols] for r in r2.counters.rows])  # NaN == NaN here
    w1, w3 = _weights(r1.run_dir)["actor"], _weights(r3.run_dir)["actor"]
    assert any(not torch.equal(w1[k], w3[k]) for k in w1)


def test_resume_continues_exactly(tmp_path):
    """Stopping after 2 learning episodes and resuming to 4 gives the same networks, optimisers and replay as one run."""
    full = train(TrainConfig(**TINY, seed=5), tmp_path / "full", progress=False, log=_quiet)
    half = TrainConfig(**{**TINY, "episodes": 2}, seed=5)
    train(half, tmp_path / "split", progress=False, log=_quiet)
    ck_half = load_checkpoint(tmp_path / "split" / "checkpoint.pt")
    assert ck_half["counters"]["updates"] > 0  # the interrupted run had already learned
    resumed = train(TrainConfig(**TINY, seed=5), tmp_path / "split", resume=True, progress=False, log=_quiet)
    assert resumed.counters.updates == full.counters.updates
    a, b = load_checkpoint(tmp_path / "full" / "checkpoint.pt"), load_checkpoint(tmp_path / "split" / "checkpoint.pt")
    _assert_same_agent(a["agent"], b["agent"])
    for k in a["agent"]["actor_opt"]["state"]:
        torch.testing.assert_close(a["agent"]["actor_opt"]["state"][k]["exp_avg"],
                                   b["agent"]["actor_opt"]["state"][k]["exp_avg"], rtol=0, atol=0)
    np.testing.assert_array_equal(a["replay"][0]["tuples"], b["replay"][0]["tuples"])
    assert a["rng"]["replay"] == b["rng"]["replay"]


def test_policy_every_delays_actor_steps(tmp_path, monkeypatch):
    """policy_every = 3 trains the actor on every third update after actor_delay, the critic on every one."""
    from learn.ddpg import CentralisedDDPG

    flags: list[bool] = []
    real = CentralisedDDPG.update_parts

    def spy(self, parts, bc_weight=0.0, train_actor=True):
        flags.append(train_actor)
        return real(self, parts, bc_weight, train_actor)

    monkeypatch.setattr(CentralisedDDPG, "update_parts", spy)
    res = train(TrainConfig(**TINY, seed=2, policy_every=3, actor_delay=2), tmp_path / "d", progress=False, log=_quiet)
    assert len(flags) == res.counters.updates > 6
    assert flags == [i >= 2 and (i - 2) % 3 == 0 for i in range(len(flags))]
    with pytest.raises(ConfigError, match="policy_every must be in 1..1000"):
        TrainConfig(policy_every=0).validate()


def test_resume_refuses_changed_config(tmp_path):
    """Resuming with a different learning rate is refused with a message naming its flag."""
    train(TrainConfig(**TINY, seed=1), tmp_path / "r", progress=False, log=_quiet)
    with pytest.raises(ConfigError, match="different --lr-actor; only --episodes"):
        train(TrainConfig(**{**TINY, "lr_actor": 0.5}, seed=1), tmp_path / "r", resume=True, progress=False)


@pytest.mark.parametrize("field, value, words", [
    ("gamma", 1.0, "gamma must be in [0, 1)"),
    ("tau", 0.0, "tau must be in (0, 1]"),
    ("batch_size", 0, "batch_size must be >= 1"),
    ("n_robots", 0, "n_robots must be in 1..1024"),
    ("world", "mars", "world must be one of"),
    ("actor_hidden", (), "actor_hidden must be one or more widths"),
    ("replay_size", 100, "must hold at least one episode per env"),
    ("lr_critic", -1.0, "lr_critic must be > 0"),
])
def test_bad_config_values_rejected(field, value, words):
    """Each bad value raises ConfigError with a one-line message naming the problem."""
    with pytest.raises(ConfigError) as e:
        TrainConfig(**{field: value}).validate()
    assert words in str(e.value) and "\n" not in str(e.value)


def test_config_file_and_presets():
    """Unknown keys and mistyped values in a config are refused; presets override defaults."""
    with pytest.raises(ConfigError, match="unknown training config field"):
        TrainConfig.from_dict({"learning_rate": 1e-3})
    with pytest.raises(ConfigError, match="batch_size must be an integer, got 3.5 \\(a float\\)"):
        TrainConfig.from_dict({"batch_size": 3.5})
    with pytest.raises(ConfigError, match="unknown training preset"):
        from_preset("slow")
    assert from_preset("fast").n_envs > 1 and from_preset("default").n_envs == 1
    assert from_preset("default").batch_size == 32 and from_preset("default").tau == 0.001


def test_config_values_are_checked_exactly():
    """Config file values go through kiloforge.validate: an int field takes only integers, a float field finite
    numbers (an integer becomes a float), a tuple field integers (n_robots also one), a str field strings."""
    c = TrainConfig.from_dict({"n_robots": 4, "tau": 1, "actor_hidden": [16, 8], "exp_name": "a"})
    assert c.n_robots == (4,) and c.tau == 1.0 and isinstance(c.tau, float) and c.actor_hidden == (16, 8)
    for d, words in (({"n_envs": True}, "n_envs must be an integer, got true (a boolean)"),
                     ({"tau": float("nan")}, "tau must be a finite number"),
                     ({"actor_hidden": [16, 8.0]}, "actor_hidden[1] must be an integer, got 8.0 (a float)"),
                     ({"actor_hidden": 16}, "actor_hidden must be a list of integers, got 16 (an integer)"),
                     ({"exp_name": 5}, "exp_name must be a string, got 5 (an integer)")):
        with pytest.raises(ConfigError) as e:
            TrainConfig.from_dict(d)
        assert str(e.value) == words or str(e.value).startswith(words), str(e.value)


def test_cli_bad_value_is_one_line_exit_2():
    """`python -m learn train --gamma 1.5` prints one error line (no traceback) and exits 2."""
    out = subprocess.run([sys.executable, "-m", "learn", "train", "--gamma", "1.5", "--out", "/nonexistent/x"],
                         cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "gamma must be in [0, 1)" in lines[0], out.stderr
    out = subprocess.run([sys.executable, "-m", "learn", "train", "--batch-size", "many"],
                         cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1
    assert out.stderr.startswith("python -m learn train: error: --batch-size: invalid literal"), out.stderr


def test_cli_smoke_train_plot_evaluate(tmp_path, capsys):
    """The CLI trains (CSV, PNG, loadable artifacts), refuses to overwrite, plots two seeds, and evaluates."""
    runs = []
    for seed in (1, 2):
        run = tmp_path / f"run{seed}"
        assert main(["train", *TINY_ARGS, "--seed", str(seed), "--out", str(run)]) == 0
        runs.append(run)
    run = runs[0]
    assert capsys.readouterr().out.splitlines()[-1].startswith(  # the last line exports the run's result
        f"  next: python -m export --policy {runs[1] / 'policy_best.npz'} --out kilobot_policy.c")
    for name in ("metrics.csv", "learning_curve.png", "policy_best.npz", "policy_last.npz", "checkpoint.pt",
                 "config.json", "world.json", "summary.json"):
        assert (run / name).is_file(), name
    rows = read_metrics(run)
    assert len(rows) >= 2 and rows[-1]["env_steps"] == 6 * 20 and rows[-1]["updates"] > 0
    pol = load_policy(run / "policy_best.npz")
    assert pol.t_prev == 3 and pol.hidden == [8] and pol.provenance["seed"] == 1
    assert pol.provenance["config"]["n_robots"] == 2 and "eval_return" in pol.provenance["eval"]
    assert load_policy(run / "policy_last.npz").provenance["env_steps"] == 120
    assert json.loads((run / "summary.json").read_text())["updates_per_s"] > 0

    assert main(["train", *TINY_ARGS, "--out", str(run)]) == 2  # the run exists: refuse, say --resume
    assert "--resume" in capsys.readouterr().err

    png = tmp_path / "curves.png"
    assert main(["plot", str(runs[0]), str(runs[1]), "--out", str(png)]) == 0
    assert png.stat().st_size > 1000

    ev = tmp_path / "eval"
    assert main(["evaluate", "--policy", str(run / "policy_best.npz"), "--robots", "3", "--episodes", "2",
                 "--steps", "12", "--n-envs", "2", "--out", str(ev), "--quiet"]) == 0
    res = json.loads((ev / "evaluation.json").read_text())
    assert set(res["robots"]["3"]["metrics"]) == {"run1/policy_best", "hand-written", "hand-written pusher", "random"}
    for name in ("reward_over_time_3.png", "returns_box_3.png", "coverage_3.png", "episode_run1_policy_best_3.gif"):
        assert (ev / name).stat().st_size > 500, name
    assert main(["evaluate", "--policy", str(tmp_path / "missing.npz"), "--out", str(ev)]) == 2


def test_tensorboard_logs_every_metrics_row(tmp_path):
    """--tensorboard writes event files under the run directory with one scalar per metrics column and row."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    run = tmp_path / "tb"
    assert main(["train", *TINY_ARGS, "--tensorboard", "--out", str(run)]) == 0
    assert list((run / "tensorboard").glob("events.out.tfevents.*"))
    acc = EventAccumulator(str(run / "tensorboard"))
    acc.Reload()
    tags = set(acc.Tags()["scalars"])
    assert {"eval_return", "eval_final_coverage", "critic_loss", "updates", "updates_per_s"} <= tags
    rows = read_metrics(run)
    ev = acc.Scalars("eval_return")
    assert [e.step for e in ev] == [int(r["env_steps"]) for r in rows]
    np.testing.assert_allclose([e.value for e in ev], [r["eval_return"] for r in rows], rtol=1e-4, atol=1e-6)
    assert main(["train", *TINY_ARGS, "--out", str(tmp_path / "plain")]) == 0
    assert not (tmp_path / "plain" / "tensorboard").exists()  # off by default


def test_device_option(tmp_path, capsys):
    """--device cpu trains end to end; --device cuda without a GPU is one line, exit 2."""
    assert main(["train", *TINY_ARGS, "--device", "cpu", "--episodes", "2", "--out", str(tmp_path / "cpu")]) == 0
    if not torch.cuda.is_available():
        assert main(["train", *TINY_ARGS, "--device", "cuda", "--out", str(tmp_path / "gpu")]) == 2
        err = capsys.readouterr().err
        assert "no CUDA GPU" in err and err.count("\n") == 1
        assert not (tmp_path / "gpu").exists()


def test_time_budget_bar_in_a_log(tmp_path, capsys):
    """With --max-minutes the trainer's bar measures the time budget too, and in a log it writes no \\r."""
    train(TrainConfig(**{**TINY, "max_minutes": 10.0}).validate(), tmp_path / "run", progress=True)
    err = capsys.readouterr().err
    assert "\r" not in err and "\x1b" not in err
    lines = [l for l in err.splitlines() if l.startswith("run:") or l.startswith("run ")]
    assert lines and all("<" in l for l in lines)  # elapsed<remaining of the budget bar
    assert re.search(r"\b120/\d[\d,]* step", lines[-1]), lines[-1]


@pytest.mark.parametrize("init,result", [("", "policy_best.npz"), ("runs/a/policy_best.npz", "policy_last.npz")])
def test_last_line_exports_the_runs_result(init, result, tmp_path, capsys):
    """The trainer's last line exports the run's result: policy_best.npz, or a fine-tune's (--init-policy) policy_last.npz."""
    from learn.cli import _report, report_es
    from learn.config import ESConfig
    from learn.rundir import Counters, RunResult, result_policy

    for name in ("policy_best.npz", "policy_last.npz"):
        (tmp_path / name).write_bytes(b"")
    cfg = ESConfig(init_policy=init)
    assert result_policy(cfg) == result
    _report(RunResult(tmp_path, Counters(), "done"), report_es, "python -m learn train-es", cfg)
    lines = capsys.readouterr().out.splitlines()
    assert lines[-2:] == [f"  result: {tmp_path / result}",
                          f"  next: python -m export --policy {tmp_path / result} --out kilobot_policy.c   "
                          "(the firmware C of the run's result)"]
