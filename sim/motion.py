"""The motor schedule: how (u_left, u_right) becomes kilolib motor modes over one control period.

Vibration motors do not run proportionally to duty cycle, so a continuous command is realised by
switching between kilolib's calibrated modes over the ticks of a period (docs/design.md, step 4 "Act"):

* ``turn`` ticks of pivoting first (left when u_left > u_right: ``set_motors(kilo_turn_left, 0)``;
  right otherwise), so the heading change matches the thesis's k_angular = u_left - u_right;
* then ``straight`` ticks of ``set_motors(kilo_straight_left, kilo_straight_right)`` for
  k_linear = (u_left + u_right) / 2, capped so that turn + straight <= period;
* then stop for the rest of the period.

Everything is integer arithmetic on the uint8 commands the int8 network produces (u = q / 255
... q in 0..255), with multiply-and-shift instead of division, so the firmware, the emulator and the
simulator's ``kilobot`` preset compute identical schedules. The C template renders
:func:`schedule_constants` and the same two formulas.
"""
from __future__ import annotations

import numpy as np

MODE_STOP = 0
MODE_STRAIGHT = 1
MODE_LEFT = 2  #: pivot counter-clockwise (heading increases): set_motors(kilo_turn_left, 0)
MODE_RIGHT = 3  #: pivot clockwise: set_motors(0, kilo_turn_right)

SCHEDULE_SHIFT = 16


def schedule_constants(period_ticks: int) -> tuple[int, int]:
    """(K_TURN, K_STRAIGHT): fixed-point factors so that ticks = (x * K + 2^15) >> 16.

    turn ticks ≈ |ul - ur| / 255 * P and straight ticks ≈ (ul + ur) / 510 * P.

    >>> schedule_constants(31)
    (7967, 3984)
    """
    assert 1 <= period_ticks <= 255, f"period_ticks must be in 1..255, got {period_ticks}"
    k_turn = (period_ticks * (1 << SCHEDULE_SHIFT) + 127) // 255
    k_straight = (period_ticks * (1 << SCHEDULE_SHIFT) + 255) // 510
    return k_turn, k_straight


def action_to_u8(u: np.ndarray) -> np.ndarray:
    """Float command in [0, 1] → uint8 0..255, round half up, saturating.

    >>> action_to_u8(np.array([0.0, 0.5, 1.0, 1.2])).tolist()
    [0, 128, 255, 255]
    """
    q = np.floor(np.asarray(u, np.float64) * 255.0 + 0.5)
    return np.minimum(np.maximum(q, 0.0), 255.0).astype(np.uint8)  # np.clip's wrapper costs more than the work


def schedule(ul: np.ndarray, ur: np.ndarray, period_ticks: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(turn_ticks, turn_mode, straight_ticks), each shaped like ``ul`` (uint8 commands).

    >>> t, m, s = schedule(np.array([255, 0, 128]), np.array([0, 0, 128]), 31)
    >>> t.tolist(), m.tolist(), s.tolist()
    ([31, 0, 0], [2, 3, 3], [0, 0, 16])
    """
    ul = np.asarray(ul).astype(np.int32)
    ur = np.asarray(ur).astype(np.int32)
    k_turn, k_straight = schedule_constants(period_ticks)
    half = 1 << (SCHEDULE_SHIFT - 1)
    turn = (np.abs(ul - ur) * k_turn + half) >> SCHEDULE_SHIFT
    turn = np.minimum(turn, period_ticks)
    straight = ((ul + ur) * k_straight + half) >> SCHEDULE_SHIFT
    straight = np.minimum(straight, period_ticks - turn)
    mode = np.where(ul > ur, MODE_LEFT, MODE_RIGHT)
    return turn.astype(np.uint8), mode.astype(np.uint8), straight.astype(np.uint8)


def mode_at_tick(turn: np.ndarray, turn_mode: np.ndarray, straight: np.ndarray, tick: int) -> np.ndarray:
    """Motor mode during tick ``tick`` (0-based) of the period, shaped like ``turn``."""
    t = np.int32(tick)
    return np.where(t < turn, turn_mode,
                    np.where(t < turn.astype(np.int32) + straight, MODE_STRAIGHT, MODE_STOP)).astype(np.uint8)
