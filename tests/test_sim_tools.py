"""Tests of the simulator tools: rollout, baselines, metrics, rendering."""
from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from sim.baselines import HandWrittenSearcher, RandomPolicy, SearcherParams, make_policy
from sim.config import OBS_NBR_SENSING, OBS_TARGET, OBS_WALL, preset
from sim.env import SwarmEnv
from sim.metrics import compare, summarise
from sim.tasks.localisation_metrics import episode_metrics, final_coverage, time_to_find
from sim.tasks import get_task
from sim.rollout import HistoryActor, SwarmPolicy, rollout
from sim import render


def _obs(cfg, B=1, M=1, wall=0.0, target=-1.0, nbr=0.0):
    o = np.zeros((B, M, cfg.obs_dim), np.float32)
    o[..., OBS_WALL], o[..., OBS_TARGET], o[..., OBS_NBR_SENSING] = wall, target, nbr
    return o


# --- baselines ---------------------------------------------------------------------------------

def test_random_policy_actions_in_unit_square():
    """RandomPolicy returns (B, M, 2) commands in [0, 1] that vary."""
    cfg = preset("thesis")
    pol = RandomPolicy()
    assert isinstance(pol, SwarmPolicy)
    pol.reset(3, 5, np.random.default_rng(1))
    a = pol.act(_obs(cfg, 3, 5))
    assert a.shape == (3, 5, 2)
    assert a.min() >= 0.0 and a.max() <= 1.0 and a.std() > 0.1


@pytest.mark.parametrize("name", ["thesis", "kilobot"])
def test_handwritten_actions_in_unit_square_over_an_episode(name):
    """The hand-written searcher only ever sends commands in [0, 1] (whole short episodes)."""
    cfg = preset(name, episode_steps=60)
    res = rollout(SwarmEnv(cfg, 2, 6, seed=0), HandWrittenSearcher(cfg), 2, seed=3, record=True)
    acts = res.trajectories.actions
    assert acts.shape == (2, 60, 6, 2)
    assert acts.min() >= 0.0 and acts.max() <= 1.0
    assert (acts.sum(-1) > 0).mean() > 0.3  # it actually moves


def test_handwritten_stops_when_target_is_close():
    """A robot that hears the target within stop_dist stops both motors and stays stopped."""
    cfg = preset("thesis")
    pol = HandWrittenSearcher(cfg, SearcherParams(stop_dist=0.8))
    pol.reset(1, 2, np.random.default_rng(0))
    pol.act(_obs(cfg, 1, 2))
    o = _obs(cfg, 1, 2)
    o[0, 0, OBS_TARGET] = 0.5  # robot 0 hears the target at half the comm radius
    a = pol.act(o)
    np.testing.assert_array_equal(a[0, 0], [0.0, 0.0])
    assert a[0, 1].sum() > 0  # robot 1 keeps searching
    a = pol.act(o)
    np.testing.assert_array_equal(a[0, 0], [0.0, 0.0])


def test_handwritten_turns_at_wall():
    """With the wall flag set a searching robot pivots (u_left != u_right) instead of going straight."""
    cfg = preset("thesis")
    pol = HandWrittenSearcher(cfg, SearcherParams(run_min_steps=50, run_max_steps=50))
    pol.reset(1, 8, np.random.default_rng(0))
    pol.act(_obs(cfg, 1, 8))
    a = pol.act(_obs(cfg, 1, 8))  # mid-run or tumbling, no wall
    a = pol.act(_obs(cfg, 1, 8, wall=1.0))
    turning = a[0, :, 0] != a[0, :, 1]
    assert turning.all(), a


def test_handwritten_u_turns_after_losing_target():
    """A robot moving inside the target range that loses the target pivots back."""
    cfg = preset("thesis")
    pol = HandWrittenSearcher(cfg, SearcherParams(stop_dist=0.2, uturn_steps=4))
    pol.reset(1, 1, np.random.default_rng(0))
    pol.act(_obs(cfg, target=0.9))
    pol.act(_obs(cfg, target=0.8))  # improving: straight on
    a = [pol.act(_obs(cfg)) for _ in range(4)]  # lost: four pivot periods
    assert all(x[0, 0, 0] != x[0, 0, 1] for x in a)


def _commands(pol, cfg, targets):
    """One robot's commands for a sequence of heard target distances (fractions of the range; -1: not heard)."""
    pol.reset(1, 1, np.random.default_rng(0))
    return [tuple(pol.act(_obs(cfg, target=t))[0, 0]) for t in targets]


STRAIGHT, STOP = (1.0, 1.0), (0.0, 0.0)


def test_pusher_keeps_pushing_until_the_distance_grows_by_the_margin():
    """At the target a pusher drives on while the distance stays within push_margin of its best; the searcher tumbles."""
    cfg = preset("kilobot")
    heard = [0.99, 0.97, 0.97, 0.98, 0.99, 0.9999]  # improving, then blocked: equal, +0.01, +0.02, then +0.03
    push = _commands(make_policy("pusher", cfg, push_margin=0.025), cfg, heard)
    assert push[:5] == [STRAIGHT] * 5 and push[5][0] != push[5][1], push
    plain = _commands(make_policy("baseline", cfg), cfg, heard)
    assert plain[2][0] != plain[2][1], plain  # no improvement: the searcher tumbles at once


def test_pusher_pushed_out_of_its_band_drives_on():
    """A settled pusher that hears the target beyond stop_dist drives straight on; the searcher holds still there."""
    cfg = preset("kilobot")
    heard = [0.99, 0.93, 0.93, 0.96, 0.96]  # entering, stopping within 0.94, pushed out to 0.96
    assert _commands(make_policy("pusher", cfg), cfg, heard)[1:] == [STOP, STOP, STRAIGHT, STRAIGHT]
    assert _commands(make_policy("baseline", cfg, stop_dist=0.94), cfg, heard)[1:] == [STOP] * 4


def test_pusher_pushed_out_counts_its_margin_from_where_it_was_pushed_to():
    """Pushed out by more than push_margin, a pusher drives on from there instead of tumbling at its next period."""
    cfg = preset("kilobot")
    heard = [0.99, 0.93, 0.93, 0.99, 0.99, 0.99, 0.99]  # stopped within 0.94, pushed out by 0.06, held there
    assert _commands(make_policy("pusher", cfg, push_margin=0.05), cfg, heard)[1:] == [STOP, STOP] + [STRAIGHT] * 4


def test_turn_sign_2_alternates_at_the_target_and_turns_left_elsewhere():
    """turn_sign 2: tumbles at the target go right, left, right, …; away from it every turn is to the left."""
    cfg = preset("kilobot")
    pol = HandWrittenSearcher(cfg, SearcherParams(turn_sign=2, tumble_max_steps=1, stop_dist=0.1, settle_patience=99))
    worse = [0.5] + [0.5 + 0.01 * k for k in range(1, 9)]  # every period a little further: a tumble each other period
    turns = [c for c in _commands(pol, cfg, worse) if c[0] != c[1]]
    assert len(turns) >= 3 and all(a != b for a, b in zip(turns, turns[1:])), turns
    pol = HandWrittenSearcher(cfg, SearcherParams(turn_sign=2, run_min_steps=1, run_max_steps=1))
    away = [c for c in _commands(pol, cfg, [-1.0] * 12) if c[0] != c[1]]
    assert away and set(away) == {(1.0, 0.0)}, away


def test_handwritten_beats_random_on_final_coverage():
    """Thesis world, 4 robots, 32 episodes: the searcher's final coverage beats random by a wide margin."""
    cfg = preset("thesis")
    env = SwarmEnv(cfg, 32, 4, seed=0)
    hand = rollout(env, make_policy("baseline", cfg), 32, seed=11).metrics().summary()["final_coverage"]
    rand = rollout(env, make_policy("random", cfg), 32, seed=11).metrics().summary()["final_coverage"]
    assert hand.mean - hand.ci95 > rand.mean + rand.ci95  # confidence intervals do not overlap
    assert hand.mean > 0.6 and hand.mean > rand.mean + 0.4, (hand, rand)


# --- rollout -----------------------------------------------------------------------------------

def test_rollout_is_deterministic_per_seed():
    """Same seed ⇒ identical rewards, coverage and paths; another seed ⇒ different ones."""
    cfg = preset("thesis", episode_steps=30)
    env = SwarmEnv(cfg, 2, 4, seed=0)
    a = rollout(env, make_policy("baseline", cfg), 3, seed=5, record=True)
    rollout(env, make_policy("random", cfg), 2, seed=99)  # disturb the env's state in between
    b = rollout(SwarmEnv(cfg, 2, 4, seed=7), make_policy("baseline", cfg), 3, seed=5, record=True)
    c = rollout(env, make_policy("baseline", cfg), 3, seed=6)
    assert a.rewards.shape == (3, 30) and a.success.shape == (3, 30)
    np.testing.assert_array_equal(a.rewards, b.rewards)
    np.testing.assert_array_equal(a.success, b.success)
    np.testing.assert_array_equal(a.trajectories.positions, b.trajectories.positions)
    assert not np.array_equal(a.trajectories.positions[:, 0], rollout(
        env, make_policy("baseline", cfg), 3, seed=6, record=True).trajectories.positions[:, 0])
    assert c.rewards.shape == (3, 30)


def test_rollout_records_consistent_trajectories():
    """Recorded in-range flags agree with the recorded positions, and coverage with the flags."""
    cfg = preset("thesis", episode_steps=40)
    res = rollout(SwarmEnv(cfg, 2, 5, seed=0), make_policy("baseline", cfg), 2, seed=1, record=True)
    tr = res.trajectories
    d = np.linalg.norm(tr.positions - tr.target[:, :, None, :], axis=-1)  # (E, T+1, M)
    clear = np.abs(d - cfg.comm_radius_mm) > 1e-3  # float32 positions: skip exact-boundary cases
    np.testing.assert_array_equal(tr.in_range[clear], (d <= cfg.comm_radius_mm)[clear])
    assert tr.in_range.any() and not tr.in_range.all()
    np.testing.assert_allclose(res.success, tr.in_range[:, 1:].mean(-1))
    assert np.all(np.abs(tr.positions) <= cfg.arena_half_mm + 1e-3)


def test_history_actor_feeds_algorithm4_history():
    """HistoryActor gives act_fn (0, o1) × t_prev first, then appends (its previous action, o2)."""
    cfg = preset("thesis")
    seen = []

    def act_fn(h):
        seen.append(h.copy())
        return np.full(h.shape[:-1] + (2,), 0.25) + 0.5 * (len(seen) - 1)  # 0.25, then 0.75

    actor = HistoryActor(act_fn, 3, cfg)
    actor.reset(1, 2, np.random.default_rng(0))
    o1 = np.random.default_rng(1).random((1, 2, cfg.obs_dim)).astype(np.float32)
    o2 = o1 + 1.0
    a1 = actor.act(o1)
    actor.act(o2)
    D = cfg.tuple_dim
    h1 = seen[0].reshape(1, 2, 3, D)
    for k in range(3):
        np.testing.assert_array_equal(h1[..., k, :2], 0.0)
        np.testing.assert_array_equal(h1[..., k, 2:], o1)
    h2 = seen[1].reshape(1, 2, 3, D)
    np.testing.assert_array_equal(h2[..., 2, :2], a1.astype(np.float32))  # newest tuple last
    np.testing.assert_array_equal(h2[..., 2, 2:], o2)
    np.testing.assert_array_equal(h2[..., 1, 2:], o1)
    actor.reset(1, 2, np.random.default_rng(0))
    actor.act(o2)
    np.testing.assert_array_equal(seen[2].reshape(1, 2, 3, D)[..., 0, 2:], o2)  # fresh history


# --- metrics -----------------------------------------------------------------------------------

def test_time_to_find_hand_computed():
    """First step with any robot in range, 1-based; the episode length when never found."""
    cov = np.array([[0, 0, 0.25, 0, 0.5], [0, 0, 0, 0, 0], [0.5, 0, 0, 0, 0], [0, 0, 0, 0, 1]])
    np.testing.assert_array_equal(time_to_find(cov), [3, 5, 1, 5])


def test_final_coverage_hand_computed():
    """Final coverage averages the last 25 % of steps (ceil): 8 steps → last 2, 10 steps → last 3."""
    c8 = np.array([[1, 1, 1, 1, 1, 1, 0.5, 0.0], [0, 0, 0, 0, 0, 0, 1, 1]])
    np.testing.assert_allclose(final_coverage(c8), [0.25, 1.0])
    c10 = np.array([[0, 0, 0, 0, 0, 0, 0, 0.3, 0.6, 0.9]])
    np.testing.assert_allclose(final_coverage(c10), [0.6])


def test_episode_metrics_and_summary():
    """Returns, found flags and 95 % CI (Student t) from toy per-step arrays."""
    r = np.array([[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]])
    c = np.array([[0.0, 0.5, 1.0], [0.0, 0.0, 0.0]])
    m = episode_metrics(r, c)
    np.testing.assert_allclose(m.returns, [6.0, 0.0])
    np.testing.assert_array_equal(m.found, [True, False])
    np.testing.assert_array_equal(m.time_to_find, [2, 3])
    s = m.summary()["return"]
    assert s.mean == 3.0 and s.n == 2
    assert s.std == pytest.approx(np.sqrt(18.0))
    assert s.ci95 == pytest.approx(12.706 * np.sqrt(18.0) / np.sqrt(2))
    one = summarise(np.array([4.0]))
    assert (one.mean, one.std, one.ci95) == (4.0, 0.0, 0.0)


def test_compare_table_lists_every_policy():
    """compare() prints a header and one row per policy with its final coverage."""
    c = np.array([[0.0, 1.0, 1.0, 1.0]])
    t = compare({"alpha": episode_metrics(np.zeros((1, 4)), c), "beta": episode_metrics(np.zeros((1, 4)), 0 * c)},
                get_task("localisation").columns)
    lines = t.splitlines()
    assert len(lines) == 3 and "final cov" in lines[0]
    assert lines[1].startswith("alpha") and "1.000" in lines[1]
    assert lines[2].startswith("beta") and "0.000" in lines[2]


# --- rendering ---------------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["thesis", "kilobot"])
def test_renders_are_valid_png_and_gif(tmp_path, name):
    """Trajectory and coverage PNGs open in Pillow; the episode GIF has several frames."""
    cfg = preset(name, episode_steps=25)
    res = rollout(SwarmEnv(cfg, 2, 3, seed=0), make_policy("baseline", cfg), 2, seed=0, record=1)
    tr = res.trajectories
    assert tr.positions.shape == (1, 26, 3, 2)
    p1 = render.plot_trajectories(tr.positions[0], tr.target[0], cfg, tmp_path / "t.png")
    p2 = render.plot_success({"baseline": res.success, "zero": 0 * res.success}, tmp_path / "c.png")
    p3 = render.animate_episode(tr.positions[0], tr.headings[0], tr.target[0], tr.in_range[0], cfg,
                                tmp_path / "e.gif", max_frames=10)
    for p in (p1, p2):
        with Image.open(p) as im:
            assert im.format == "PNG" and im.size[0] > 200
    with Image.open(p3) as im:
        assert im.format == "GIF" and im.n_frames == 10
    assert sorted(f.name for f in tmp_path.iterdir()) == ["c.png", "e.gif", "t.png"]  # no temp files left


def test_render_frame_highlights_robots_in_range():
    """render_frame returns an RGB frame whose pixels change colour when a robot is in range."""
    cfg = preset("kilobot")
    pos = np.array([[0.0, 0.0], [150.0, 150.0]])
    f_out = render.render_frame(pos, np.zeros(2), np.array([-200.0, -200.0]), np.array([False, False]), cfg)
    f_in = render.render_frame(pos, np.zeros(2), np.array([-200.0, -200.0]), np.array([True, False]), cfg)
    assert f_out.ndim == 3 and f_out.shape[2] == 3 and f_out.dtype == np.uint8
    orange = np.array([0xE6, 0x55, 0x0D])
    assert not np.all(f_out == orange, axis=-1).any()
    assert np.all(f_in == orange, axis=-1).sum() > 20
