"""A task's own observation features (sim.table_features): declared in a task file, computed the same way by the
simulator's two observation paths, and by its C block and its emulator twin bit for bit."""
from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pytest

from export.codegen.render import POLICY_FILE, render_firmware
from export.contract import firmware as fwspec
from export.verify.emulator import FirmwareEmulator
from export.verify.hostbuild import StreamSpec, build_host, compare, compiler, random_inputs, run_host
from kiloforge.errors import InputError
from sim.config import preset
from sim.env import SwarmEnv
from sim.features import TASK_FEATURES, input_names
from sim.table_features import NeighbourTable
from sim.tasks import get_task
from tests.fixtures import synthetic_qpolicy

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = f"{ROOT / 'examples' / 'dispersion.py'}:Dispersion"
needs_gcc = pytest.mark.skipif(compiler() is None, reason="no host C compiler (gcc) installed")


def test_table_reductions_equal_a_loop_over_robots():
    """count, min, max and sum per robot equal a plain loop over the entries, with empty robots at their default."""
    rng = np.random.default_rng(5)
    robot = rng.integers(0, 9, 40)
    dist = rng.integers(0, 256, 40).astype(float)
    t = NeighbourTable.of(robot, dist, 12)
    for r in range(12):
        mine = dist[robot == r]
        assert t.count()[r] == mine.size
        assert t.sum(t.dist_mm)[r] == mine.sum()
        assert t.min(t.dist_mm, empty=-1.0)[r] == (mine.min() if mine.size else -1.0)
        assert t.max(t.dist_mm, empty=-1.0)[r] == (mine.max() if mine.size else -1.0)
    shuffled = np.random.default_rng(1).permutation(40)
    t2 = NeighbourTable.of(robot[shuffled], dist[shuffled], 12)
    np.testing.assert_array_equal(t2.robot, t.robot)  # the entries' order is canonical
    np.testing.assert_array_equal(t2.dist_mm, t.dist_mm)


def test_example_task_registers_its_feature_in_the_layout():
    """Resolving the example registers 'crowd': one input between wall and rbf, named in the ONNX input names."""
    task = get_task(EXAMPLE)
    world = task.world(preset("kilobot"))
    assert "crowd" in TASK_FEATURES and world.features == ("wall", "crowd", "rbf")
    assert world.obs_dim == 2 + world.n_rbf and world.obs_slice("crowd") == slice(1, 2)
    assert input_names(world)[:3] == ["wall", "crowd", "rbf_0"]


@pytest.mark.parametrize("world,overrides", [("kilobot", {"arena_half_mm": 150.0, "neighbour_table_size": 3}),
                                             ("thesis", {"neighbour_table_size": 4})])
def test_fast_observe_equals_events_path_with_a_task_feature(world, overrides):
    """The task's feature is the same bit for bit on the fast path and on sim.events.observe, tables overflowing."""
    task = get_task(EXAMPLE)
    cfg = task.world(preset(world, **overrides))
    fast = SwarmEnv(cfg, 3, 20, seed=4, fast_observe=True, task=task)
    slow = SwarmEnv(cfg, 3, 20, seed=4, fast_observe=False, task=task)
    o1, o2 = fast.reset()[0], slow.reset()[0]
    seen = set()
    rng = np.random.default_rng(2)
    for _ in range(6):
        np.testing.assert_array_equal(o1, o2)
        seen |= set(np.unique(o1[..., cfg.obs_slice("crowd")]).tolist())
        a = rng.random((3, 20, 2))
        o1, o2 = fast.step(a)[0], slow.step(a)[0]
    assert len(seen) >= 3  # crowded start: several crowd levels occur


@needs_gcc
def test_task_feature_block_equals_its_emulator_twin_on_fuzzed_streams(tmp_path):
    """The example's C block and its integer twin agree byte for byte on fuzzed streams (distances 0..255, full
    tables), and the feature takes every level 0..4."""
    task = get_task(EXAMPLE)
    world = task.world(preset("kilobot", neighbour_table_size=5, period_ticks=12))
    qp = synthetic_qpolicy(world, 4, (8,), seed=3)
    c = render_firmware(qp, generator_version="t")[POLICY_FILE]
    assert "crowd_n" in c and "#define KF_OBS_CROWD 1u" in c
    exe = build_host(c, tmp_path, name="crowd")
    inputs = random_inputs(np.random.default_rng(np.random.SeedSequence(8)), world.period_ticks, (),
                           StreamSpec(n_robots=48, n_steps=60, rate=0.9), fwspec.DEFAULT_MSG_TYPE,
                           world.comm_radius_mm, world.light_threshold)
    want = FirmwareEmulator(qp, inputs.uids, inputs.calib).run(inputs)
    got = run_host(exe, inputs, world.period_ticks, world.obs_dim, fill="random:3")
    np.testing.assert_array_equal(got.steps, want.steps, err_msg=compare(want, got))
    np.testing.assert_array_equal(got.ticks, want.ticks, err_msg=compare(want, got))
    one = int(qp.one_q)
    assert set(np.unique(want.obs[..., 1]).tolist()) == {k * one // 4 for k in range(5)}


BAD_FEATURES = {
    "no firmware block": ('firmware = ""', "has no firmware block"),
    "never writes its input": ('firmware = "    i = 0u;\\n"', r"never writes obs\[KF_OBS_CROWD_\w+\]"),
    "a built-in's name": ('name = "rbf"', "has the name of a built-in feature"),
    "a name C cannot take": ('name = "Crowd-2"', "must match"),
    "Jinja in its C": ('firmware_decl = "{% include x %}"', "without"),
}


def _bad_task(tmp_path: Path, line: str) -> str:
    src = (ROOT / "examples" / "dispersion.py").read_text()
    src = src.replace("\n\nclass Dispersion(Task):", "\n" + textwrap.indent(line, "    ") + "\n\n\nclass Dispersion(Task):", 1)
    name = f"crowd_{tmp_path.name[-12:].lower().replace('-', '_')}"  # a name of its own: 'crowd' is the example's
    src = src.replace('"crowd"', f'"{name}"').replace("KF_OBS_CROWD", f"KF_OBS_{name.upper()}")
    path = tmp_path / "bad_task.py"
    path.write_text(src)
    return f"{path}:Dispersion"


@pytest.mark.parametrize("case", BAD_FEATURES, ids=list(BAD_FEATURES))
def test_a_bad_task_feature_is_one_line(case, tmp_path):
    """A task feature without a firmware block, with a bad name or text, is refused when the task is resolved."""
    line, message = BAD_FEATURES[case]
    with pytest.raises(InputError, match=message) as e:
        get_task(_bad_task(tmp_path, line))
    assert "\n" not in str(e.value) and "bad_task.py:Dispersion" in str(e.value)


def test_a_feature_returning_the_wrong_shape_is_one_line(tmp_path):
    """A reference() of the wrong shape stops the episode with one line naming the feature and the method."""
    spec = _bad_task(tmp_path, "def reference(self, table, cfg):\n    return np.zeros(table.n)")
    task = get_task(spec)
    env = SwarmEnv(task.world(preset("kilobot")), 1, 8, seed=0, task=task)
    with pytest.raises(InputError, match=r"^feature 'crowd_\w+': reference\(\) must return shape \(8, 1\), got \(8,\)$"):
        env.reset()


def test_cli_names_the_bad_feature_in_one_line(tmp_path, capsys):
    """python -m sim with a task whose feature has no firmware block: exit 2, one line, nothing written."""
    from kiloforge.sim_cli import main

    spec = _bad_task(tmp_path, 'firmware = ""')
    rc = main(["--task", spec, "--policy", "random", "--robots", "4", "--steps", "5", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "has no firmware block" in err
    assert not (tmp_path / "o").exists()
