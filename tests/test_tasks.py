"""The task interface: registry, --task resolution, artifacts that record their task, refusals."""
from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from kiloforge.errors import InputError, PolicyError
from kiloforge.policies import load_policy, save_policy
from sim.config import preset
from sim.env import SwarmEnv
from sim.tasks import LEGACY_TASK, TASKS, Task, TaskRef, get_task, task_names
from sim.tasks.localisation import Localisation

HERE = Path(__file__).parent
USER_TASK = f"{HERE / 'tasks' / 'near_beacon.py'}:NearBeacon"
SHIPPED = Path(__file__).parents[1] / "export" / "data" / "default_policy.npz"


def _run(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, cwd=cwd, timeout=300)


def test_registry_resolves_names_and_default():
    """None and 'localisation' give localisation; an unknown name is one line listing the tasks."""
    assert isinstance(get_task(None), Localisation) and isinstance(get_task("localisation"), Localisation)
    assert {"localisation", "aggregation"} <= set(TASKS) and task_names()[:2] == ["aggregation", "localisation"]
    with pytest.raises(InputError, match="unknown task 'aggregate'; choose one of: aggregation, localisation"):
        get_task("aggregate")


def test_user_task_from_file_runs_in_the_simulator():
    """path.py:Class loads a user's task, and SwarmEnv reports its own success signal."""
    task = get_task(USER_TASK)
    assert task.ref == TaskRef("near_beacon", 2) and task.primary_metric == "final_near"
    env = SwarmEnv(preset("kilobot"), 2, 4, seed=3, task=task)
    env.reset()
    _, r, _, _, info = env.step(np.full((2, 4, 2), 0.5))
    near = np.linalg.norm(env.pos - env.target[:, None], axis=-1) <= 0.5 * env.cfg.comm_radius_mm
    np.testing.assert_array_equal(info["success"], near.mean(axis=1))
    np.testing.assert_array_equal(r, info["success"].astype(np.float32))


def test_entry_point_plugin_is_found(tmp_path, monkeypatch):
    """A package's entry point in the group kiloforge.tasks is a task name."""
    (tmp_path / "my_tasks.py").write_text((HERE / "tasks" / "near_beacon.py").read_text())
    dist = tmp_path / "my_tasks-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: my-tasks\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[kiloforge.tasks]\nnear = my_tasks:NearBeacon\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert "near" in task_names()
    assert get_task("near").ref == TaskRef("near_beacon", 2)


@pytest.mark.parametrize("source, message", [
    ("class T(:\n", "syntax error at line 1"),
    ("import no_such_module_here\n", "failed to import: ModuleNotFoundError"),
    ("X = 1\n", "defines no 'T'"),
    ("T = 3\n", "is not a subclass of sim.tasks.Task"),
    ("from sim.tasks import Task\nclass T(Task):\n    name = 'x'\n    def spawn(self, env): pass\n",
     "does not define"),
    ("from sim.tasks.localisation import Localisation\nclass T(Localisation):\n    name = 'Bad Name'\n",
     "task name must match"),
    ("from sim.tasks.localisation import Localisation\nclass T(Localisation):\n    name = 'x'\n"
     "    primary_metric = 'nope'\n", "primary_metric 'nope' is not among its metrics"),
])
def test_bad_task_file_is_one_line(tmp_path, source, message):
    """A broken task file is one InputError line naming what is wrong."""
    f = tmp_path / "t.py"
    f.write_text(source)
    with pytest.raises(InputError, match=message) as e:
        get_task(f"{f}:T")
    assert "\n" not in str(e.value)


def test_wrong_success_shape_is_refused(tmp_path):
    """A task whose success is not (B,) in [0, 1] is refused by the env in one line."""
    f = tmp_path / "t.py"
    f.write_text("from sim.tasks.localisation import Localisation\nclass T(Localisation):\n    name = 'x'\n"
                 "    def step_info(self, env):\n        return {'success': env.target_dist}\n")
    env = SwarmEnv(preset("kilobot"), 2, 3, seed=0, task=get_task(f"{f}:T"))
    with pytest.raises(InputError, match=r"\['success'\] must be \(B,\) = \(2,\) values in \[0, 1\]"):
        env.reset()


def test_file_from_before_tasks_loads_as_localisation_v1():
    """The shipped default (written before tasks) records no task, loads as localisation v1, hash unchanged."""
    meta = json.loads(np.load(SHIPPED)["meta"].tobytes())
    assert "task" not in meta
    p = load_policy(SHIPPED)
    assert p.task is None and p.task_ref == LEGACY_TASK and p.hash == meta["policy_hash"]


def test_task_is_recorded_and_hashed(tmp_path):
    """A policy with a task writes it to meta, reads it back, and the hash covers it."""
    p = dataclasses.replace(load_policy(SHIPPED), task=TaskRef("near_beacon", 2))
    path = save_policy(p, tmp_path / "p.npz")
    back = load_policy(path)
    assert back.task_ref == TaskRef("near_beacon", 2) and back.hash == p.hash != load_policy(SHIPPED).hash
    z = dict(np.load(path))
    meta = json.loads(z["meta"].tobytes())
    assert meta["task"] == {"name": "near_beacon", "version": 2}
    meta["task"]["version"] = 3  # edited after training: the hash no longer matches
    z["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    np.savez(tmp_path / "edited.npz", **z)
    with pytest.raises(PolicyError, match="does not match the contents"):
        load_policy(tmp_path / "edited.npz")
    meta["task"] = {"name": "near_beacon"}
    z["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    np.savez(tmp_path / "bad.npz", **z)
    with pytest.raises(PolicyError, match="'task' must be"):
        load_policy(tmp_path / "bad.npz")


def test_commands_refuse_a_policy_of_another_task(tmp_path):
    """export, export verify and learn evaluate refuse a task mismatch in one line, exit 2, writing nothing."""
    other = save_policy(dataclasses.replace(load_policy(SHIPPED), task=TaskRef("near_beacon", 2)), tmp_path / "o.npz")
    cases = [
        (["-m", "export", "--policy", str(other), "--out", str(tmp_path / "k.c"), "--no-avr"],
         "trained for task near_beacon v2, not localisation v1"),
        (["-m", "export", "--task", USER_TASK, "--out", str(tmp_path / "k.c"), "--no-avr"],
         "task 'near_beacon' ships no policy 'default'"),
        (["-m", "export", "verify", "--task", USER_TASK, "--policy", str(SHIPPED), "--robots", "4"],
         "trained for task localisation v1, not near_beacon v2"),
        (["-m", "learn", "evaluate", "--policy", str(other), "--robots", "4", "--episodes", "2"],
         "trained for task near_beacon v2, not localisation v1"),
        (["-m", "learn", "evaluate", "--task", "nope", "--policy", "default"], "unknown task 'nope'"),
    ]
    for args, message in cases:
        r = _run(*args, cwd=tmp_path)
        assert r.returncode == 2, (args, r.stderr)
        assert message in r.stderr and len(r.stderr.strip().splitlines()) == 1, (args, r.stderr)
    assert not (tmp_path / "k.c").exists()


def test_evaluation_json_names_its_task(tmp_path):
    """evaluation.json keeps its layout and names the task; a user task's baselines are its own."""
    from learn.evaluate import evaluate_policies

    p = dataclasses.replace(load_policy(SHIPPED), task=TaskRef("near_beacon", 2))
    res = evaluate_policies({"mine": p}, [4], 2, 20, tmp_path, n_envs=2, gif=False, progress=False,
                            log=lambda s: None, task=USER_TASK)
    assert res["task"] == {"name": "near_beacon", "version": 2, "primary_metric": "final_near"}
    assert set(res["robots"]["4"]["metrics"]) == {"mine", "hand-written", "hand-written pusher", "random"}
    assert json.loads((tmp_path / "evaluation.json").read_text())["task"]["name"] == "near_beacon"


def test_task_base_requires_the_methods():
    """Task is abstract: a subclass must implement spawn, step_info, reward, state_dim and state."""
    assert Task.__abstractmethods__ == {"spawn", "step_info", "reward", "state_dim", "state"}


def test_largest_cluster_on_known_geometry():
    """Links at <= 2 body diameters chain robots into clusters; success is the largest one's share."""
    from sim.tasks.aggregation import largest_cluster, link_mm

    cfg = preset("kilobot")
    assert link_mm(cfg) == 66.0
    pos = np.array([[[0, 0], [60, 0], [120, 0], [180, 0], [-200, -200], [-200, -140], [200, 200], [0, 200]],
                    [[0, 0], [67, 0], [134, 0], [201, 0], [-200, -200], [-200, -134], [200, 200], [0, 200]]], float)
    frac, members = largest_cluster(pos, link_mm(cfg), cfg.arena_half_mm)
    np.testing.assert_array_equal(frac, [4 / 8, 2 / 8])
    np.testing.assert_array_equal(members[0], [1, 1, 1, 1, 0, 0, 0, 0])
    np.testing.assert_array_equal(members[1], [0, 0, 0, 0, 1, 1, 0, 0])


def test_aggregation_world_has_no_beacon():
    """Aggregation spawns no beacon: no beacon disc, no beacon messages, success from the robots alone."""
    from sim.tasks.aggregation import largest_cluster, link_mm

    cfg = get_task("aggregation").world(preset("kilobot"))
    env = SwarmEnv(cfg, 3, 12, seed=5, task="aggregation")
    obs, info = env.reset()
    assert env.target is None and env.target_dist is None and env.state().shape == (3, 36)
    for _ in range(3):
        obs, r, _, _, info = env.step(np.full((3, 12, 2), 0.7))
        assert not np.any(info["events"].role) and obs.shape[-1] == 1 + cfg.n_rbf  # wall and RBF only
        np.testing.assert_array_equal(info["success"], largest_cluster(env.pos, link_mm(cfg), cfg.arena_half_mm)[0])


def test_es_evaluates_in_its_tasks_world():
    """train-es's evaluation world is its training world (the task's beacon and layout) with eval_steps steps."""
    from learn.config import ESConfig

    cfg = ESConfig(task="aggregation", demo_policy="none", eval_steps=123)
    assert cfg.eval_world() == dataclasses.replace(cfg.world_config(), episode_steps=123)
    assert not cfg.eval_world().emitter


def test_hand_written_aggregator_beats_random():
    """The probabilistic aggregation rule gathers more robots than the random walk (16 robots, 8 episodes)."""
    from sim.rollout import rollout

    task = get_task("aggregation")
    cfg = task.world(dataclasses.replace(preset("kilobot"), episode_steps=300))
    env = SwarmEnv(cfg, 8, 16, seed=0, task=task)
    final = {name: rollout(env, task.make_baseline(name, cfg), 8, seed=3).metrics().summary()["final_cluster"].mean
             for name in ("aggregator", "random")}
    assert final["aggregator"] > final["random"] + 0.05, final


def test_sim_command_runs_a_beaconless_task(tmp_path):
    """python -m sim --task aggregation plays its baseline, names its metrics and records the task in metrics.json."""
    r = _run("-m", "sim", "--task", "aggregation", "--policy", "aggregator", "--robots", "6", "--episodes", "2",
             "--steps", "20", "--quiet", "--out", str(tmp_path / "out"))
    assert r.returncode == 0, r.stderr
    assert "final cluster" in r.stdout and "final cov" not in r.stdout
    m = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert m["task"] == {"name": "aggregation", "version": 1} and "final_cluster" in m["metrics"]["summary"]
    r = _run("-m", "sim", "--task", "aggregation", "--policy", "pusher", "--out", str(tmp_path / "x"))
    assert r.returncode == 2 and "--policy must be one of aggregator, random" in r.stderr


@pytest.mark.parametrize("task", ["aggregation", "phototaxis", "transport"])
def test_shipped_learned_default_is_a_policy_of_its_task(task):
    """--task T --policy default is T's shipped learned policy: T's task version, T's world layout; refused for another task."""
    from kiloforge.shipped import SHIPPED_POLICIES, load_task_policy, shipped_names

    assert "default" in shipped_names(task)
    p = load_task_policy(None, task)
    assert p.task_ref == TaskRef(task, get_task(task).version) and p.kind == "mlp"
    get_task(task).check_world(p.world)
    with pytest.raises(InputError, match=f"trained for task {task} v{get_task(task).version}, not localisation v1"):
        load_task_policy(Path(__file__).parents[1] / "export" / "data" / SHIPPED_POLICIES[task]["default"], "localisation")
