"""Sweep grids: command line and file parsing, validation errors, trials, names, the CLI without Ray."""
import json
import sys

import pytest

pytest.importorskip("torch")

from learn.config import ConfigError  # noqa: E402
from learn.sweep.cli import main_sweep  # noqa: E402
from learn.sweep.grid import build_grid, expand, labels, parse_grid_option, read_grid_file  # noqa: E402


def test_grid_option_values():
    """--grid KEY=V1,V2 splits on commas, reads JSON lists, and refuses malformed entries."""
    assert parse_grid_option("lr_actor=1e-4,3e-4") == ("lr_actor", ["1e-4", "3e-4"])
    assert parse_grid_option("actor-hidden=[[32,32],[64]]") == ("actor_hidden", [[32, 32], [64]])
    for bad in ("lr_actor", "=1", "lr_actor=", "lr_actor=1,,2", "x=[1,"):
        with pytest.raises(ConfigError):
            parse_grid_option(bad)


def test_axes_are_typed_and_canonical():
    """Values are coerced to the field's type, so the command line and a file give the same trials."""
    cli = build_grid(seeds=[1, 2], robots=[1, 2], presets=["quick"],
                     grid=["lr_actor=1e-4,3e-4", "actor_hidden=32x32,64x32"])
    assert cli.axes == {"lr_actor": [1e-4, 3e-4], "actor_hidden": [[32, 32], [64, 32]], "n_robots": [1, 2]}
    f = build_grid({"preset": "quick", "seeds": [1, 2],
                    "grid": {"lr_actor": [0.0001, 0.0003], "actor_hidden": [[32, 32], [64, 32]], "n_robots": [1, 2]}})
    assert [t.name for t in expand(cli)] == [t.name for t in expand(f)]
    assert build_grid({"grid": {"actor_hidden": [16, 16]}}).axes == {"actor_hidden": [[16, 16]]}  # one tuple


def test_trials_seed_major_with_stable_distinct_names():
    """Trials are configurations × seeds, seed-major; names are stable, distinct and shared config ids per seed."""
    g = build_grid(seeds=[3, 4], robots=[1, 2], history=[5], presets=["quick"])
    trials = expand(g)
    assert [(t.seed, t.config["n_robots"], t.config["t_prev"]) for t in trials] == \
        [(3, 1, 5), (3, 2, 5), (4, 1, 5), (4, 2, 5)]
    assert len({t.name for t in trials}) == 4 and len({t.config_id for t in trials}) == 2
    assert trials[0].config_id == trials[2].config_id
    assert trials[0].name.startswith("kilobot-m1-t5_s3_")  # the default world
    assert [t.name for t in expand(build_grid(seeds=[3, 4], robots=[1, 2], history=[5], presets=["quick"]))] == \
        [t.name for t in trials]
    # the budget is not part of a trial's identity; a field is
    assert [t.name for t in expand(build_grid(seeds=[3, 4], robots=[1, 2], history=[5], presets=["quick"],
                                              max_minutes=7))] == [t.name for t in trials]
    other = expand(build_grid(seeds=[3], robots=[1], history=[5], presets=["quick"], grid=["lr_actor=3e-4"]))
    assert other[0].name != trials[0].name
    assert trials[0].config["max_minutes"] == 5.0 and trials[0].config["n_envs"] == 16  # the quick preset


def test_labels_name_what_varies():
    """Configuration labels list the fields that differ between configurations, or the preset when none do."""
    trials = expand(build_grid(seeds=[1, 2], robots=[1, 2], presets=["quick"], grid=["episode_steps=50"]))
    assert sorted(labels(trials).values()) == ["n_robots=1", "n_robots=2"]
    assert list(labels(expand(build_grid(presets=["quick"]))).values()) == ["magddpg quick"]


@pytest.mark.parametrize("kw, message", [
    (dict(grid=["lr_actr=1e-4"]), "'lr_actr' is not a TrainConfig field of the magddpg trainer (did you mean lr_actor?)"),
    (dict(grid=["lr_actor=fast"]), "--grid lr_actor: lr_actor: cannot read 'fast' as float"),
    (dict(grid=["n_robots=1.5"]), "cannot read '1.5' as int"),
    (dict(robots=[0]), "n_robots must be in 1..1024, got 0"),
    (dict(grid=["seed=1,2"]), "'seed' has its own option: use --seeds"),
    (dict(grid=["max_minutes=3"]), "use --max-minutes"),
    (dict(robots=[1], grid=["n_robots=2"]), "--robots and --grid n_robots set the same field"),
    (dict(grid=["lr_actor=1e-4", "lr_actor=3e-4"]), "--grid lr_actor is given twice"),
    (dict(robots=[1, 1]), "lists 1 twice"),
    (dict(seeds=[1, 1]), "a seed is listed twice"),
    (dict(presets=["turbo"]), "unknown magddpg preset 'turbo'"),
    (dict(presets=["kilobot"]), "unknown magddpg preset 'kilobot'"),
    (dict(world=["mars"]), "world must be one of"),
    (dict(trainer="magrdpg", history=[5]), "--history: the magrdpg trainer has no field t_prev"),
    (dict(trainer="magrdpg", grid=["actor_hidden=8"]), "'actor_hidden' is not a RecurrentConfig field"),
    (dict(max_minutes=-1), "--max-minutes must be >= 0"),
    (dict(cpus_per_trial=0), "--cpus-per-trial must be > 0"),
    (dict(eval_robots=[0]), "--eval-robots must be robot counts"),
])
def test_bad_grids_fail_in_one_line(kw, message):
    """Bad keys and values are refused with one line naming them."""
    with pytest.raises(ConfigError) as e:
        expand(build_grid(**kw))
    assert message in str(e.value) and "\n" not in str(e.value)


def test_mixed_tasks_refused(tmp_path, capsys):
    """A grid mixing tasks is refused in one line (their metrics do not aggregate), also across runs of one --out."""
    with pytest.raises(ConfigError, match="mixes localisation, aggregation: their metrics cannot be aggregated"):
        expand(build_grid(trainer="es", presets=["quick"], grid=["task=localisation,aggregation", "demo_policy=none"]))
    out = tmp_path / "s"
    assert main_sweep(["--trainer", "es", "--preset", "quick", "--task", "aggregation", "--grid", "demo_policy=none",
                       "--out", str(out), "--dry-run"]) == 0
    grid = build_grid(trainer="es", presets=["quick"])
    from learn.sweep.aggregate import write_manifest
    out.mkdir()
    write_manifest(out, grid, expand(grid))  # a localisation sweep in this directory before
    assert main_sweep(["--trainer", "es", "--preset", "quick", "--task", "aggregation", "--grid", "demo_policy=none",
                       "--out", str(out), "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert "mixes localisation, aggregation" in err and err.count("\n") == 1


def test_magrdpg_grid():
    """The recurrent trainer's fields and presets form trials too (GRU size in the name)."""
    trials = expand(build_grid(trainer="magrdpg", presets=["guided"], robots=[2], grid=["hidden=16,32"]))
    assert [t.name.split("_s1_")[0] for t in trials] == ["kilobot-m2-gru16", "kilobot-m2-gru32"]
    assert trials[0].config["demo_policy"] == "searcher"


def test_grid_files(tmp_path):
    """JSON and TOML grid files give the same trials; unknown keys and bad files are one-line errors."""
    toml = tmp_path / "g.toml"
    toml.write_text('preset = "quick"\nseeds = [1, 2]\nmax_minutes = 2\n[grid]\nn_robots = [1, 2]\nt_prev = 5\n')
    js = tmp_path / "g.json"
    js.write_text(json.dumps({"preset": "quick", "seeds": [1, 2], "max_minutes": 2,
                              "grid": {"n_robots": [1, 2], "t_prev": 5}}))
    a, b = build_grid(read_grid_file(toml)), build_grid(read_grid_file(js))
    assert [t.name for t in expand(a)] == [t.name for t in expand(b)] and a.max_minutes == 2.0
    assert len(expand(build_grid(read_grid_file(js), seeds=[7]))) == 2  # the command line replaces the file
    (tmp_path / "bad.json").write_text('{"seeds": [1], "robots": [2]}')
    (tmp_path / "broken.toml").write_text("seeds = [1,\n")
    for name, message in (("bad.json", "unknown key(s) robots"), ("broken.toml", "cannot read grid file"),
                          ("missing.json", "cannot read grid file")):
        with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
            read_grid_file(tmp_path / name)


def test_cli_bad_grid_exits_2_before_anything(tmp_path, capsys):
    """A bad grid key: one line on stderr, exit 2, no sweep directory written."""
    out = tmp_path / "sweep"
    assert main_sweep(["--grid", "lr_actr=1", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "lr_actr" in err[0] and "did you mean lr_actor" in err[0]
    assert not out.exists()


def test_cli_without_ray_prints_install_hint(tmp_path, capsys, monkeypatch):
    """Without Ray installed the sweep exits 2 with the one-line install hint, after validating the grid."""
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    monkeypatch.delitem(sys.modules, "learn.sweep.execute", raising=False)
    assert main_sweep(["--seeds", "1", "--preset", "quick", "--out", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["python -m learn sweep: error: Ray Tune is not installed: pip install 'kiloforge[sweep]'"]
    assert not (tmp_path / "s").exists()


def test_cli_dry_run_lists_trials(tmp_path, capsys):
    """--dry-run lists every trial and its state and writes nothing."""
    assert main_sweep(["--seeds", "1", "2", "--robots", "1", "2", "--preset", "quick", "--out",
                       str(tmp_path / "s"), "--dry-run"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("4 trials in") and "4 to start" in out[0]
    assert sum(line.strip().startswith("new ") for line in out[1:]) == 4
    assert not (tmp_path / "s").exists()


def test_cli_cpus_per_trial_beyond_local_cpus(tmp_path, capsys):
    """More CPUs per trial than the local Ray has is refused before anything starts (exit 2)."""
    assert main_sweep(["--cpus-per-trial", "3", "--num-cpus", "2", "--out", str(tmp_path / "s"), "--dry-run"]) == 2
    assert "--cpus-per-trial 3 is more than the 2 CPUs of the local Ray" in capsys.readouterr().err
    assert main_sweep(["--num-cpus", "2", "--address", "auto", "--out", str(tmp_path / "s")]) == 2
    assert not (tmp_path / "s").exists()


def test_es_grid_runs_a_trial(tmp_path):
    """The ES trainer's presets form trials, and one tiny trial trains, then is finished on a rerun."""
    from learn.sweep.trial import run_trial, trial_state
    from learn.config import ESConfig

    tiny = ["episode_steps=20", "demo_robot_episodes=4", "bc_updates=5", "bc_batch=32", "generations=2", "pairs=2",
            "eval_every=1", "eval_episodes=2", "eval_steps=20", "actor_hidden=8", "t_prev=2"]
    trials = expand(build_grid(trainer="es", presets=["quick"], seeds=[1, 2], robots=[2], grid=tiny))
    assert [t.name.split("_s")[0] for t in trials] == ["kilobot-m2-t2"] * 2
    t = trials[0]
    numbers = run_trial(t.trainer, t.config, tmp_path / t.name)
    assert numbers["best_final_coverage"] >= 0
    assert trial_state(ESConfig.from_dict(t.config), tmp_path / t.name, 0) == "finished"
