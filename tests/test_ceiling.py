"""The packing ceiling (sim/tasks/ceiling.py): valid packings, the shipped table, the evaluation's column."""
from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from kiloforge.errors import InputError
from sim.tasks import ceiling, get_task
from sim.config import KILOBOT, THESIS
from sim.env import SwarmEnv
from sim.baselines import make_policy
from sim.tasks.localisation_metrics import final_coverage
from sim.rollout import rollout
from tests.fixtures import init_policy

PROB = ceiling.Packing.of(KILOBOT)


def check_packing(points: np.ndarray, dx: float, dy: float) -> None:
    """Assert the kilobot-world constraints on a beacon-frame packing, written out independently."""
    d, R, L = 2 * KILOBOT.robot_radius_mm, KILOBOT.comm_radius_mm, KILOBOT.arena_half_mm - KILOBOT.robot_radius_mm
    bx, by = L - dx, L - dy  # a beacon at these wall distances, arena coordinates
    for k, (x, y) in enumerate(points):
        ax, ay = bx + x, by + y
        assert -L <= ax <= L and -L <= ay <= L, f"disc {k} outside the walls"
        assert d <= math.hypot(x, y) <= R, f"disc {k} overlaps the beacon or is out of range"
        for x2, y2 in points[k + 1:]:
            assert math.hypot(x - x2, y - y2) >= d, f"disc {k} overlaps another"


def test_shipped_configurations_valid():
    """Every configuration in the shipped table is a valid packing of its count at its grid point."""
    t = ceiling.load_table()
    g = t.grid_mm
    for i in range(g.size):
        for j in range(g.size):
            pts = t.configs[i, j]
            pts = pts[~np.isnan(pts[:, 0])]
            assert pts.shape[0] == t.counts[i, j]
            check_packing(pts, g[i], g[j])


def test_table_matches_recomputation():
    """The shipped table equals a fresh search at three grid points (counts and configurations bit-exact)."""
    t = ceiling.load_table()
    g = t.grid_mm
    for i, j in ((0, 0), (2, 9), (g.size - 1, g.size - 1)):
        pts = ceiling.pack(t.prob, float(g[i]), float(g[j]), t.seed)
        np.testing.assert_array_equal(np.int64(pts.shape[0]), t.counts[i, j])
        np.testing.assert_array_equal(pts, t.configs[i, j, :pts.shape[0]])


def test_table_world_parameters():
    """The shipped table is for the kilobot world's bodies, range and arena, on a 5 mm grid to R."""
    t = ceiling.load_table()
    assert t.prob == PROB
    np.testing.assert_array_equal(t.grid_mm, np.arange(0.0, 86.0, 5.0))
    assert ceiling.has_ceiling(KILOBOT)


def test_envelope_monotone_and_realised():
    """Capacity never drops as the beacon moves away from a wall, and each envelope value is realised
    by a table configuration that is valid at that grid point."""
    t = ceiling.load_table()
    env, g = t.envelope, t.grid_mm
    assert np.all(np.diff(env, axis=0) >= 0) and np.all(np.diff(env, axis=1) >= 0)
    assert np.all(env >= t.counts)
    for i in range(g.size):
        for j in range(g.size):
            src = np.argwhere(t.counts[:i + 1, :j + 1] == env[i, j])[0]
            pts = t.configs[src[0], src[1]]
            check_packing(pts[~np.isnan(pts[:, 0])], g[i], g[j])


def test_open_field_and_corner_counts():
    """The search beats the best hexagonal lattice in the open and at a corner (relaxation does work)."""
    t = ceiling.load_table()
    assert t.counts[-1, -1] > ceiling._lattice(PROB, PROB.R, PROB.R).shape[0]
    assert t.counts[0, 0] < t.counts[0, -1] < t.counts[-1, -1]


def test_capacity_lookup_conservative():
    """A beacon between grid points gets the envelope at the grid point nearer the walls; far from
    walls, the open-field value."""
    t = ceiling.load_table()
    L = KILOBOT.arena_half_mm - KILOBOT.robot_radius_mm
    beacon = np.array([[L - 7.0, -(L - 12.4)], [0.0, 0.0], [L, L], [-(L - 85.0), L - 84.9]])
    cap = ceiling.capacity(KILOBOT, beacon)
    np.testing.assert_array_equal(cap, [t.envelope[1, 2], t.envelope[-1, -1], t.envelope[0, 0],
                                        t.envelope[-1, -2]])


def test_other_worlds():
    """Point robots without collisions have ceiling 1; a collision world the table was not made for is refused."""
    np.testing.assert_array_equal(ceiling.episode_ceiling(THESIS, 8, np.zeros((3, 2))), np.ones(3))
    other = dataclasses.replace(KILOBOT, comm_radius_mm=70.0)
    assert not ceiling.has_ceiling(other)
    with pytest.raises(InputError, match="no packing table for .*comm_radius_mm 70.0") as e:
        ceiling.capacity(other, np.zeros((1, 2)))
    assert "\n" not in str(e.value)


def test_mean_capacity_matches_spawn_sampling():
    """The exact mean capacity over the spawn agrees with sampling the env's beacon spawns."""
    env = SwarmEnv(KILOBOT, 2000, 1, seed=5)
    env.reset()
    sampled = ceiling.capacity(KILOBOT, env.target).mean()
    assert abs(ceiling.mean_capacity(KILOBOT) - sampled) < 0.3
    assert ceiling.mean_capacity(KILOBOT, 4) == 4.0


def test_rollout_ceiling_from_beacons():
    """A rollout's ceiling fraction is final coverage over min(M, capacity at its own beacon) / M."""
    M = 32
    world = dataclasses.replace(KILOBOT, episode_steps=8)
    r = rollout(SwarmEnv(world, 3, M, seed=0), make_policy("baseline", world), 3, seed=4)
    m = r.metrics(ceiling=True)
    cap = ceiling.capacity(world, r.emitter)
    assert np.all(cap < M)  # the ceiling binds at 32 robots
    np.testing.assert_array_equal(m.ceiling, np.minimum(M, cap) / M)
    frac = m.summary()["of_ceiling"].mean
    assert frac == pytest.approx(np.mean(final_coverage(r.success) * M / cap))


def test_evaluation_reports_ceiling(tmp_path):
    """evaluate_policies' table and JSON hold each policy's ceiling fraction, from its episodes' beacons."""
    from learn.evaluate import evaluate_policies

    pol = init_policy(KILOBOT, t_prev=1, hidden=(4,))
    lines: list[str] = []
    res = evaluate_policies({"tiny": pol}, [32], episodes=2, steps=8, out_dir=tmp_path, seed=3, gif=False,
                            progress=False, log=lines.append)
    assert "of ceiling" in "\n".join(lines)
    saved = json.loads((tmp_path / "evaluation.json").read_text())
    row = saved["robots"]["32"]
    world = dataclasses.replace(KILOBOT, episode_steps=8)
    r = rollout(SwarmEnv(world, 2, 32, seed=3), make_policy("baseline", world), 2, seed=3)
    want = ceiling.episode_ceiling(world, 32, r.emitter)
    assert np.all(want < 1.0)
    for name in ("tiny", "hand-written", "hand-written pusher", "random"):  # a taped-down beacon: the same episodes, the same ceilings
        np.testing.assert_allclose(row["ceiling"][name], want, atol=1e-6)
        assert "of_ceiling" in row["metrics"][name]["summary"]
    got = row["metrics"]["hand-written"]["summary"]["of_ceiling"]["mean"]
    assert got == pytest.approx(np.mean(final_coverage(r.success) / want))
    assert saved["packing"]["open_capacity"] == ceiling.open_capacity(KILOBOT)
    assert res["packing"]["mean_capacity"] == pytest.approx(ceiling.mean_capacity(KILOBOT))


def test_packing_note_only_where_the_task_has_a_ceiling_elsewhere():
    """The 'no packing ceiling' note is localisation's (a world its table does not cover), never another task's."""
    from learn.evaluate import evaluate_policies

    uncovered = dataclasses.replace(KILOBOT, arena_half_mm=300.0)  # not the packing table's arena
    for task, world, want in (("localisation", uncovered, True), ("aggregation", KILOBOT, False)):
        spec = get_task(task)
        pol = dataclasses.replace(init_policy(spec.world(world), t_prev=1, hidden=(4,)), task=spec.ref)
        lines: list[str] = []
        evaluate_policies({"tiny": pol}, [3], episodes=1, steps=4, out_dir=None, seed=3, gif=False, progress=False,
                          log=lines.append, task=task, baselines=False)
        assert any("no packing ceiling" in line for line in lines) == want, (task, lines)
