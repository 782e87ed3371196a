"""Tests of the contract modules: sim.config, sim.events, sim.history, sim.motion."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from sim.config import (ACTION_DIM, OBS_NBR_SENSING, OBS_RBF, OBS_TARGET, OBS_WALL, PRESETS, ROLE_SEARCHER,
                        ROLE_TARGET, WorldConfig, preset)
from sim.events import HeardEvents, observe, rbf, summarise
from sim.history import History
from sim.motion import (MODE_LEFT, MODE_RIGHT, MODE_STOP, MODE_STRAIGHT, action_to_u8, mode_at_tick, schedule,
                        schedule_constants)


# --- config ------------------------------------------------------------------------------------
def test_presets_have_consistent_dims():
    """Every preset's obs/tuple/history/state widths follow the documented layout."""
    for name, cfg in PRESETS.items():
        assert cfg.obs_dim == OBS_RBF + cfg.n_rbf == 14, name
        assert cfg.tuple_dim == ACTION_DIM + cfg.obs_dim
        assert cfg.history_dim(20) == 20 * cfg.tuple_dim
        assert cfg.state_dim(7) == 2 + 21
        assert cfg.rbf_centres_mm.shape == (cfg.n_rbf,)
        assert cfg.rbf_centres_mm[0] == cfg.rbf_lo_mm and cfg.rbf_centres_mm[-1] == cfg.rbf_hi_mm


def test_preset_unknown_name_and_overrides():
    """preset() rejects unknown names (naming the choices) and applies overrides."""
    with pytest.raises(ValueError, match="unknown preset 'nope'.*kilobot.*thesis"):
        preset("nope")
    assert preset("kilobot", msg_loss=0.0).msg_loss == 0.0
    assert preset("thesis") is PRESETS["thesis"]


def test_config_roundtrip_and_unknown_field():
    """to_dict/from_dict round-trips; unknown keys are named in the error."""
    cfg = preset("kilobot", dist_noise_mm=1.5)
    assert WorldConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ValueError, match="bogus"):
        WorldConfig.from_dict({**cfg.to_dict(), "bogus": 1})


@pytest.mark.parametrize("field,value,word", [
    ("arena_half_mm", 0.0, "arena_half_mm"), ("msg_loss", 1.0, "msg_loss"), ("n_rbf", 0, "n_rbf"),
    ("period_ticks", 0, "period_ticks"), ("comm_radius_mm", 300.0, "comm_radius_mm"),
])
def test_config_rejects_bad_values(field, value, word):
    """Out-of-range config values raise ValueError naming the field."""
    with pytest.raises(ValueError, match=word):
        dataclasses.replace(preset("thesis"), **{field: value})


def test_tick_level_needs_message_period():
    """A tick-level world without a message period is refused."""
    with pytest.raises(ValueError, match="msg_period_ticks"):
        preset("kilobot", msg_period_ticks=0)


# --- events ------------------------------------------------------------------------------------
def _ev(rows):
    """HeardEvents from rows (env, rx, sender, tick, dist, role, flag)."""
    a = np.array(rows, dtype=np.float64).reshape(-1, 7)
    return HeardEvents(a[:, 0].astype(np.int32), a[:, 1].astype(np.int32), a[:, 2].astype(np.int32),
                       a[:, 3].astype(np.int16), a[:, 4], a[:, 5].astype(np.uint8), a[:, 6].astype(np.uint8))


def test_rbf_matches_thesis_formula():
    """rbf() is ψ_k(d) = exp(-(d-μ_k)²/2σ²) / norm inside the radius and 0 beyond."""
    cfg = preset("thesis")
    d = np.array([0.0, 3.3, 17.2, 40.0, 40.01])
    got = rbf(cfg, d)
    for n, dm in enumerate(d):
        for k in range(cfg.n_rbf):
            mu = cfg.rbf_lo_mm + k * (cfg.rbf_hi_mm - cfg.rbf_lo_mm) / (cfg.n_rbf - 1)
            want = math.exp(-(dm - mu) ** 2 / (2 * cfg.rbf_sigma_mm ** 2)) / cfg.rbf_norm if dm <= 40 else 0.0
            assert got[n, k] == pytest.approx(want, rel=1e-12, abs=1e-300)


def test_summarise_latest_wins_and_table_full():
    """Latest message of a sender wins; a full table drops new senders; the target slot keeps the latest."""
    cfg = preset("thesis", neighbour_table_size=2)
    S, T = ROLE_SEARCHER, ROLE_TARGET
    ev = _ev([
        (0, 0, 1, 0, 10.0, S, 0), (0, 0, 2, 1, 20.0, S, 0), (0, 0, 3, 2, 30.0, S, 1),  # 3: table full
        (0, 0, 1, 3, 11.0, S, 1),  # latest from 1
        (0, 0, -1, 1, 25.0, T, 0), (0, 0, -1, 4, 26.0, T, 0),  # target twice: latest
    ])
    s = summarise(ev, cfg, 1, 2)
    assert s.target_heard[0, 0] and not s.target_heard[0, 1]
    assert s.target_dist_mm[0, 0] == 26.0
    got = sorted(zip(s.table_sender.tolist(), s.table_dist_mm.tolist(), s.table_flag.tolist()))
    assert got == [(1, 11.0, 1), (2, 20.0, 0)]


def test_observe_fields():
    """observe() fills wall (with dropout keeping the last flag), target, neighbour flag and RBF."""
    cfg = preset("thesis")
    S, T = ROLE_SEARCHER, ROLE_TARGET
    ev = _ev([(0, 0, 1, 0, 12.0, S, 1), (0, 0, -1, 0, 20.0, T, 0), (0, 1, 0, 0, 12.0, S, 0)])
    light = np.array([[800, -1]])
    obs, flags = observe(ev, light, np.array([[0.0, 1.0]]), cfg)
    assert obs.dtype == np.float32 and obs.shape == (1, 2, 14)
    assert obs[0, 0, OBS_WALL] == 1.0 and obs[0, 1, OBS_WALL] == 1.0  # -1 keeps the previous 1
    assert obs[0, 0, OBS_TARGET] == np.float32(0.5) and obs[0, 1, OBS_TARGET] == -1.0
    assert obs[0, 0, OBS_NBR_SENSING] == 1.0 and obs[0, 1, OBS_NBR_SENSING] == 0.0
    np.testing.assert_array_equal(obs[0, 0, OBS_RBF:], rbf(cfg, np.array([12.0]))[0].astype(np.float32))
    np.testing.assert_array_equal(flags, [[1, 0]])


# --- history -----------------------------------------------------------------------------------
def test_history_init_repeats_first_tuple():
    """reset() fills all T_prev slots with (a=0, o_1) (Algorithm 4)."""
    h = History(3, 2)
    o1 = np.array([[[5.0, 6.0]]])
    flat = h.reset(o1)
    np.testing.assert_array_equal(flat, [[[0, 0, 5, 6] * 3]])


def test_history_push_order_oldest_first():
    """push() drops the oldest tuple and appends the newest at the end."""
    h = History(3, 1)
    h.reset(np.array([[[1.0]]]))
    h.push(np.array([[[0.1, 0.2]]]), np.array([[[2.0]]]))
    flat = h.push(np.array([[[0.3, 0.4]]]), np.array([[[3.0]]]))
    np.testing.assert_allclose(flat, [[[0, 0, 1, 0.1, 0.2, 2, 0.3, 0.4, 3]]], rtol=1e-6)
    flat = h.push(np.array([[[0.5, 0.6]]]), np.array([[[4.0]]]))
    np.testing.assert_allclose(flat, [[[0.1, 0.2, 2, 0.3, 0.4, 3, 0.5, 0.6, 4]]], rtol=1e-6)


def test_history_reset_where_only_done_envs():
    """reset_where() re-initialises only the envs marked done."""
    h = History(2, 1)
    h.reset(np.array([[[1.0]], [[1.0]]]))
    h.push(np.ones((2, 1, 2)), np.array([[[2.0]], [[2.0]]]))
    h.reset_where(np.array([True, False]), np.array([[[9.0]], [[9.0]]]))
    flat = h.flat()
    np.testing.assert_array_equal(flat[0], [[0, 0, 9, 0, 0, 9]])
    np.testing.assert_array_equal(flat[1], [[0, 0, 1, 1, 1, 2]])


# --- motion ------------------------------------------------------------------------------------
def test_action_to_u8_edges():
    """Half-up rounding and saturation of float commands to uint8."""
    u = np.array([-0.5, 0.0, 0.5 / 255, 0.49 / 255, 0.5, 1.0, 1.5, 254.5 / 255])
    np.testing.assert_array_equal(action_to_u8(u), [0, 0, 1, 0, 128, 255, 255, 255])


def test_schedule_extremes():
    """Stop, full straight, full turns and the turn-before-straight cap."""
    ul = np.array([0, 255, 255, 0, 200, 1])
    ur = np.array([0, 255, 0, 255, 100, 0])
    turn, mode, straight = schedule(ul, ur, 31)
    np.testing.assert_array_equal(turn, [0, 0, 31, 31, 12, 0])
    np.testing.assert_array_equal(mode, [MODE_RIGHT, MODE_RIGHT, MODE_LEFT, MODE_RIGHT, MODE_LEFT, MODE_LEFT])
    np.testing.assert_array_equal(straight, [0, 31, 0, 0, 18, 0])


def test_schedule_never_exceeds_period_all_commands():
    """For all 65536 command pairs and several periods, turn + straight <= P and turn matches |ul-ur|."""
    ul, ur = np.meshgrid(np.arange(256), np.arange(256))
    for P in (1, 16, 31, 255):
        turn, mode, straight = schedule(ul, ur, P)
        assert (turn.astype(int) + straight <= P).all()
        want = np.floor(np.abs(ul - ur) / 255 * P + 0.5)
        assert np.abs(turn - np.minimum(want, P)).max() <= 1
        assert ((mode == MODE_LEFT) == (ul > ur)).all()


def test_schedule_constants_small_and_large_period():
    """Fixed-point factors for the extreme periods."""
    assert schedule_constants(1) == ((65536 + 127) // 255, (65536 + 255) // 510)
    assert schedule_constants(255)[0] == 65536
    with pytest.raises(AssertionError):
        schedule_constants(0)


def test_mode_at_tick_sequence():
    """Turn ticks first, then straight ticks, then stop."""
    turn, mode, straight = np.array([2]), np.array([MODE_RIGHT]), np.array([3])
    modes = [int(mode_at_tick(turn, mode, straight, k)[0]) for k in range(7)]
    assert modes == [MODE_RIGHT] * 2 + [MODE_STRAIGHT] * 3 + [MODE_STOP] * 2
