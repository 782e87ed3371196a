"""Sweep aggregation on synthetic run directories: statistics over seeds, trial states, table, curves."""
import json
import math

import pytest

pytest.importorskip("torch")

from learn.config import ConfigError  # noqa: E402
from learn.sweep.aggregate import aggregate, stats, write_manifest  # noqa: E402
from learn.sweep.cli import main_sweep  # noqa: E402
from learn.sweep.grid import build_grid, expand  # noqa: E402
from learn.sweep.trial import trial_state  # noqa: E402
from learn.train import rows_to_csv  # noqa: E402

T975_2 = 4.303  # Student t quantile t_{0.975} with 2 degrees of freedom


def _row(steps: int, ret: float, cov: float, wall: float = 10.0) -> dict:
    return {"env_steps": steps, "episodes": steps // 200, "updates": 0, "wall_s": wall, "eval_return": ret,
            "eval_return_std": 0.0, "eval_final_coverage": cov, "eval_mean_coverage": cov,
            "eval_time_to_find": 1.0, "eval_found_rate": 1.0, "train_return": 0.0, "critic_loss": 0.0,
            "q_mean": 0.0, "env_steps_per_s": 1.0, "updates_per_s": 1.0}


def _fake_run(run_dir, cfg: dict, returns, coverages, finished: bool = True) -> None:
    """A run directory as the trainer leaves it (the checkpoint's content is never read by the sweep)."""
    run_dir.mkdir(parents=True)
    rows = [_row(1000 * (k + 1), r, c) for k, (r, c) in enumerate(zip(returns, coverages))]
    (run_dir / "config.json").write_text(json.dumps(cfg))
    (run_dir / "metrics.csv").write_text(rows_to_csv(rows))
    (run_dir / "checkpoint.pt").write_bytes(b"")
    if finished:
        total = cfg["warmup_episodes"] + cfg["episodes"]
        (run_dir / "summary.json").write_text(json.dumps({"stopped": "done", "episodes": total, "wall_s": 10.0}))


def test_stats_by_hand():
    """mean, sample std and the Student-t 95 % CI; std and CI undefined for one seed."""
    s = stats([4.0, 6.0, 5.0])
    assert s["n"] == 3 and s["mean"] == pytest.approx(5.0) and s["std"] == pytest.approx(1.0)
    assert s["ci95"] == pytest.approx([5 - T975_2 / math.sqrt(3), 5 + T975_2 / math.sqrt(3)], abs=1e-9)
    assert stats([2.0]) == {"n": 1, "mean": 2.0, "std": None, "ci95": None}
    assert stats([float("nan")])["n"] == 0


def test_aggregate_synthetic_sweep(tmp_path):
    """Per-configuration statistics over finished seeds, per-seed values, states, table and curve PNG."""
    grid = build_grid(seeds=[1, 2, 3], robots=[1, 2], presets=["quick"])
    trials = expand(grid)
    write_manifest(tmp_path, grid, trials)
    by = {(t.config["n_robots"], t.seed): t for t in trials}
    # n_robots 1: three finished seeds
    _fake_run(tmp_path / by[1, 1].name, by[1, 1].config, [1.0, 4.0, 2.0], [0.1, 0.5, 0.3])
    _fake_run(tmp_path / by[1, 2].name, by[1, 2].config, [2.0, 3.0, 6.0], [0.2, 0.4, 0.6])
    _fake_run(tmp_path / by[1, 3].name, by[1, 3].config, [5.0, 5.0, 5.0], [0.7, 0.8, 0.9])
    # n_robots 2: one finished, one unfinished (no summary: killed after a checkpoint), one not started
    _fake_run(tmp_path / by[2, 1].name, by[2, 1].config, [10.0, 8.0], [0.5, 0.25])
    _fake_run(tmp_path / by[2, 2].name, by[2, 2].config, [99.0], [1.0], finished=False)

    s = aggregate(tmp_path, log=lambda _m: None)
    c1, c2 = sorted(s["configurations"], key=lambda c: c["label"])
    assert (c1["label"], c1["finished"], c1["trials"], c1["seeds"]) == ("n_robots=1", 3, 3, [1, 2, 3])
    m = c1["metrics"]
    h = T975_2 / math.sqrt(3)
    # best return per seed: 4, 6, 5 (the first of equal bests); last: 2, 6, 5
    assert m["best_return"]["per_seed"] == {"1": 4.0, "2": 6.0, "3": 5.0}
    assert m["best_return"]["mean"] == pytest.approx(5.0) and m["best_return"]["std"] == pytest.approx(1.0)
    assert m["best_return"]["ci95"] == pytest.approx([5 - h, 5 + h])
    sd_last = math.sqrt(((2 - 13 / 3) ** 2 + (6 - 13 / 3) ** 2 + (5 - 13 / 3) ** 2) / 2)
    assert m["last_return"]["mean"] == pytest.approx(13 / 3) and m["last_return"]["std"] == pytest.approx(sd_last)
    assert m["last_return"]["ci95"] == pytest.approx([13 / 3 - h * sd_last, 13 / 3 + h * sd_last])
    # final coverage at the best evaluation: 0.5, 0.6, 0.7; at the last: 0.3, 0.6, 0.9
    assert m["best_final_coverage"]["mean"] == pytest.approx(0.6)
    assert m["best_final_coverage"]["std"] == pytest.approx(0.1)
    assert m["last_final_coverage"]["mean"] == pytest.approx(0.6)
    assert m["last_final_coverage"]["std"] == pytest.approx(0.3)
    # one finished seed: a mean, no spread; the unfinished trial's 99 does not count
    assert (c2["finished"], c2["trials"], c2["seeds"]) == (1, 3, [1])
    assert c2["metrics"]["best_return"] == {"n": 1, "mean": 10.0, "std": None, "ci95": None, "per_seed": {"1": 10.0}}
    assert c2["metrics"]["last_final_coverage"]["mean"] == 0.25
    status = {(r["config_id"], r["seed"]): r["status"] for r in s["trials"]}
    assert status[by[2, 2].config_id, 2] == "unfinished" and status[by[2, 3].config_id, 3] == "not started"
    assert s["totals"] == {"trials": 6, "finished": 4, "unfinished": 1, "not started": 1}

    on_disk = json.loads((tmp_path / "summary.json").read_text())
    assert on_disk["configurations"] == json.loads(json.dumps(s["configurations"]))
    table = (tmp_path / "table.txt").read_text()
    assert "5.00 ± 1.00 [2.52, 7.48]" in table and "n_robots=2     2     unfinished   99.00" in table
    assert (tmp_path / "learning_curves.png").stat().st_size > 1000


def test_trial_state_and_budget(tmp_path):
    """new / resume / finished from the run directory; a run stopped on time has finished its budget only."""
    t = expand(build_grid(presets=["quick"]))[0]
    from learn.config import TrainConfig

    cfg = TrainConfig.from_dict(t.config)
    d = tmp_path / "r"
    assert trial_state(cfg, d, 5.0) == "new"
    _fake_run(d, t.config, [1.0], [0.1], finished=False)
    assert trial_state(cfg, d, 5.0) == "resume"
    (d / "summary.json").write_text(json.dumps({"stopped": "time", "episodes": 64, "wall_s": 299.5}))
    assert trial_state(cfg, d, 5.0) == "finished"  # within a second of 5 minutes
    assert trial_state(cfg, d, 10.0) == "resume"  # a bigger budget continues it
    assert trial_state(cfg, d, 0.0) == "resume"  # no budget: until all episodes are done
    (d / "summary.json").write_text(json.dumps({"stopped": "interrupted", "episodes": 64, "wall_s": 400}))
    assert trial_state(cfg, d, 5.0) == "resume"


def test_cli_aggregate(tmp_path, capsys):
    """--aggregate DIR writes summary.json of an existing sweep; a directory without a manifest is refused."""
    grid = build_grid(seeds=[1], presets=["quick"])
    trials = expand(grid)
    write_manifest(tmp_path, grid, trials)
    _fake_run(tmp_path / trials[0].name, trials[0].config, [3.0], [0.5])
    assert main_sweep(["--aggregate", str(tmp_path)]) == 0
    assert "magddpg quick  1/1" in capsys.readouterr().out
    assert json.loads((tmp_path / "summary.json").read_text())["totals"] == {"trials": 1, "finished": 1}
    (tmp_path / "empty").mkdir()
    assert main_sweep(["--aggregate", str(tmp_path / "empty")]) == 2
    with pytest.raises(ConfigError, match="not a sweep directory"):
        aggregate(tmp_path / "empty")


def test_aggregate_task_file_sweep(tmp_path, capsys):
    """A plug-in task's sweep aggregates its own metric; --aggregate imports its file only when --task names it."""
    from pathlib import Path

    spec = f"{Path(__file__).parents[1] / 'examples' / 'dispersion.py'}:Dispersion"
    grid = build_grid(trainer="es", seeds=[1, 2], presets=["quick"], task=[spec], grid=["demo_policy=none"])
    trials = expand(grid)
    write_manifest(tmp_path, grid, trials)
    for t, alone in zip(trials, (0.25, 0.75)):
        rows = [{**_row(1000, 1.0, 0.0), "eval_final_alone": alone}]
        (tmp_path / t.name).mkdir()
        (tmp_path / t.name / "metrics.csv").write_text(rows_to_csv(rows))
        (tmp_path / t.name / "checkpoint.pt").write_bytes(b"")
        (tmp_path / t.name / "summary.json").write_text(json.dumps({"episodes": 10 ** 9}))
    assert main_sweep(["--aggregate", str(tmp_path)]) == 2
    assert "never imported" in capsys.readouterr().err
    assert main_sweep(["--aggregate", str(tmp_path), "--task", "aggregation"]) == 2
    assert "--task aggregation is not the task of the sweep's trials" in capsys.readouterr().err
    assert main_sweep(["--aggregate", str(tmp_path), "--task", spec]) == 0
    assert "best final alone" in capsys.readouterr().out
    (c,) = json.loads((tmp_path / "summary.json").read_text())["configurations"]
    assert c["metrics"]["best_final_alone"]["per_seed"] == {"1": 0.25, "2": 0.75}
    assert c["metrics"]["best_final_alone"]["mean"] == pytest.approx(0.5)


def test_refuses_run_dir_of_another_config(tmp_path, capsys):
    """A trial directory holding a run of a different configuration stops the sweep before Ray (exit 2)."""
    t = expand(build_grid(presets=["quick"]))[0]
    _fake_run(tmp_path / t.name, {**t.config, "lr_actor": 0.5}, [1.0], [0.1])
    assert main_sweep(["--preset", "quick", "--out", str(tmp_path), "--dry-run"]) == 2
    assert "holds a run with a different lr_actor" in capsys.readouterr().err
