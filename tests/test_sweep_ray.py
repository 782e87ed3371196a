"""Sweeps on a local Ray (one session for the module): a tiny end-to-end sweep, resume skipping finished trials,
TensorBoard scalars in every trial."""
import json

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("ray")
pytest.importorskip("ray.tune")

from learn.sweep.cli import main_sweep  # noqa: E402
from learn.sweep.grid import build_grid, expand  # noqa: E402
from learn.sweep.trial import run_trial  # noqa: E402
from learn.train import read_metrics, train  # noqa: E402
from learn.config import TrainConfig  # noqa: E402

#: trials of a few seconds: 20-step episodes, 2 envs, 3 evaluations
TINY = ["world=thesis", "episode_steps=20", "n_envs=2", "warmup_episodes=2", "episodes=4", "eval_every=40",
        "eval_episodes=2", "replay_size=400", "batch_size=8", "actor_hidden=8x8", "critic_hidden=16x16",
        "updates_per_step=0.5"]
ARGS = ["--preset", "quick", "--seeds", "1", "2", "--grid", *TINY, "--quiet"]


def _tiny_trials():
    return expand(build_grid(presets=["quick"], seeds=[1, 2], grid=TINY))


def test_tiny_sweep_end_to_end(ray_session, tmp_path, capsys):
    """Two trials on local Ray: ordinary run directories, summary.json over both seeds, curves, evaluation."""
    out = tmp_path / "sweep"
    assert main_sweep([*ARGS, "--out", str(out), "--eval-robots", "3", "--eval-episodes", "2",
                       "--eval-steps", "10"]) == 0
    trials = _tiny_trials()
    for t in trials:
        names = {p.name for p in (out / t.name).iterdir()}
        assert {"config.json", "world.json", "metrics.csv", "checkpoint.pt", "policy_best.npz", "policy_last.npz",
                "summary.json", "learning_curve.png", "evaluation"} <= names
        assert json.loads((out / t.name / "summary.json").read_text())["episodes"] == 6
    s = json.loads((out / "summary.json").read_text())
    assert s["totals"] == {"trials": 2, "finished": 2}
    (c,) = s["configurations"]
    best = {str(t.seed): max(r["eval_return"] for r in read_metrics(out / t.name)) for t in trials}
    assert c["metrics"]["best_return"]["per_seed"] == pytest.approx(best)
    assert c["metrics"]["best_return"]["mean"] == pytest.approx(np.mean(list(best.values())))
    assert c["metrics"]["best_return"]["std"] == pytest.approx(np.std(list(best.values()), ddof=1))
    assert (out / "learning_curves.png").stat().st_size > 1000
    ev = s["evaluation"]["robots"]["3"]
    for t in trials:
        own = json.loads((out / t.name / "evaluation" / "evaluation.json").read_text())
        assert ev["magddpg quick"]["return"]["per_seed"][str(t.seed)] == \
            own["robots"]["3"]["metrics"][t.name]["summary"]["return"]["mean"]
    assert {"hand-written (thesis)", "random (thesis)"} <= set(ev)
    assert (out / "eval_reward_over_time_3.png").exists() and (out / "eval_returns_box_3.png").exists()
    assert "magddpg quick  2/2" in (out / "table.txt").read_text()


def test_resume_skips_finished_and_resumes_unfinished(ray_session, tmp_path):
    """A finished trial is left alone; a half-trained one resumes from its checkpoint and ends as an uninterrupted run."""
    out = tmp_path / "sweep"
    done, half = _tiny_trials()
    run_trial(done.trainer, done.config, out / done.name)  # finished before the sweep
    short = TrainConfig.from_dict({**half.config, "episodes": 2})  # stopped halfway: 4 of 6 episodes
    train(short, out / half.name, progress=False, log=lambda _m: None)
    before = {p.name: p.stat().st_mtime_ns for p in (out / done.name).iterdir()}
    half_rows = read_metrics(out / half.name)

    assert main_sweep([*ARGS, "--out", str(out)]) == 0
    assert {p.name: p.stat().st_mtime_ns for p in (out / done.name).iterdir()} == before  # untouched
    tune_trials = {p.name for p in next((out / "ray_tune").iterdir()).iterdir() if p.is_dir()}
    assert tune_trials == {half.name}  # Ray never ran the finished trial
    cols = ("env_steps", "updates", "eval_return", "eval_final_coverage")
    table = lambda rows: [[r[c] for c in cols] for r in rows]  # noqa: E731
    rows = read_metrics(out / half.name)
    assert table(rows[:len(half_rows)]) == table(half_rows) and len(rows) > len(half_rows)
    reference = train(TrainConfig.from_dict(half.config), tmp_path / "reference", progress=False, log=lambda _m: None)
    np.testing.assert_array_equal(table(rows), table(read_metrics(reference.run_dir)))
    assert json.loads((out / "summary.json").read_text())["totals"] == {"trials": 2, "finished": 2}

    mtimes = lambda: {(t.name, p.name): p.stat().st_mtime_ns for t in (done, half) for p in (out / t.name).iterdir()}  # noqa: E731
    before = mtimes()
    assert main_sweep([*ARGS, "--out", str(out)]) == 0  # nothing left: no trial runs again
    assert mtimes() == before


def test_tensorboard_in_every_trial(ray_session, tmp_path):
    """--grid tensorboard=true: every trial's run directory gets event files with one eval_return per metrics row."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    out = tmp_path / "sweep"
    grid = [*TINY, "tensorboard=true"]
    assert main_sweep(["--preset", "quick", "--seeds", "1", "2", "--grid", *grid, "--quiet", "--out", str(out)]) == 0
    trials = expand(build_grid(presets=["quick"], seeds=[1, 2], grid=grid))
    assert len(trials) == 2
    for t in trials:
        run = out / t.name
        assert list((run / "tensorboard").glob("events.out.tfevents.*"))
        acc = EventAccumulator(str(run / "tensorboard"))
        acc.Reload()
        rows = read_metrics(run)
        ev = acc.Scalars("eval_return")
        assert [e.step for e in ev] == [int(r["env_steps"]) for r in rows]
        np.testing.assert_allclose([e.value for e in ev], [r["eval_return"] for r in rows], rtol=1e-4, atol=1e-6)


def test_aggregation_sweep_reports_its_metric(ray_session, tmp_path):
    """A tiny ES sweep of --task aggregation: trials, tables, JSON and evaluation name final_cluster, not coverage."""
    out = tmp_path / "sweep"
    tiny = ["episode_steps=20", "demo_policy=none", "generations=2", "pairs=2", "eval_every=1", "eval_episodes=2",
            "eval_steps=20", "actor_hidden=8", "t_prev=2"]
    assert main_sweep(["--trainer", "es", "--preset", "quick", "--task", "aggregation", "--robots", "3",
                       "--seeds", "1", "2", "--grid", *tiny, "--quiet", "--out", str(out),
                       "--eval-robots", "3", "--eval-episodes", "2", "--eval-steps", "10"]) == 0
    trials = expand(build_grid(trainer="es", presets=["quick"], task=["aggregation"], robots=[3], seeds=[1, 2],
                               grid=tiny))
    s = json.loads((out / "summary.json").read_text())
    assert s["totals"] == {"trials": 2, "finished": 2}
    (c,) = s["configurations"]
    assert set(c["metrics"]) == {"best_return", "last_return", "best_final_cluster", "last_final_cluster"}
    best = {}
    for t in trials:
        rows = read_metrics(out / t.name)
        best[str(t.seed)] = max(rows, key=lambda r: r["eval_return"])["eval_final_cluster"]
    assert c["metrics"]["best_final_cluster"]["per_seed"] == pytest.approx(best)
    assert all(0 < v <= 1 for v in best.values())  # at least one robot is in the largest cluster
    table = (out / "table.txt").read_text()
    assert "best final cluster" in table and "coverage" not in table
    ev = s["evaluation"]["robots"]["3"]
    assert set(ev) == {"es quick", "hand-written (kilobot)", "random (kilobot)"}
    assert all(set(e) == {"return", "final_cluster"} for e in ev.values())


def test_progress_lines(capsys):
    """Without a terminal, progress is one line per change: done / running / pending, failures, best so far."""
    from learn.sweep.execute import Progress

    p = Progress(total=4, done=1)
    p.started("a")
    p.result("a", {"best_return": 2.5})
    p.result("a", {"best_return": 1.0})  # not better: no new line
    p.finished("a", True)
    p.started("b")
    p.finished("b", False)
    p.close()
    assert capsys.readouterr().out.splitlines() == [
        "sweep: 1/4 done, 0 running, 3 pending",
        "sweep: 1/4 done, 1 running, 2 pending",
        "sweep: 1/4 done, 1 running, 2 pending; best return 2.50 (a)",
        "sweep: 2/4 done, 0 running, 2 pending; best return 2.50 (a)",
        "sweep: 2/4 done, 1 running, 1 pending; best return 2.50 (a)",
        "sweep: 2/4 done, 0 running, 1 pending, 1 failed; best return 2.50 (a)",
    ]
