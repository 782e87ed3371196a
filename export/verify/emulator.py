"""A bit-exact NumPy model of the generated Kilobot program, vectorised over R robots.

:class:`FirmwareEmulator` reproduces ``kilobot_policy.c`` (and, for emitter uids, the emitter's own program)
integer for integer: the rx filter and bounded rx queue, the receive rules, the int8 observation,
the actor input tuple ``[ACT[q_prev], obs]``, the actor kind's int8 control step with its state
(:meth:`kiloforge.actors.base.QuantizedActor.step_int`: an MLP's history ring, a recurrent cell's
state), the motor schedule applied tick by tick (with ``spinup_motors``), the LED and the outgoing
message bytes with their CRC. The host build (:mod:`export.verify.hostbuild`) and the AVR build
(:mod:`export.verify.avr`) run the same event streams and must give the same bytes.

Tick model (what ``firmware_templates/host/harness.c`` does): setup() sets the whole state whatever
memory held before (:meth:`FirmwareEmulator.reset` is that state) and until it has run the program
hears and sends nothing; then for global tick T = 0, 1, 2, ...

1. ``kilo_ticks = T`` and ``loop()`` runs once: it drains the rx queue into the period's table; if
   T is a control tick (``T = k * period_ticks`` with k >= 1) it runs the control step (observe from
   the table, clear it, the actor's step, motor schedule for ticks T .. T+P-1, LED, message);
   then it applies this tick's motor mode. During the first period (T < P) the robot stands still
   and listens: Algorithm 4 observes o_1 before the first action, as ``SwarmEnv.reset`` does;
2. the messages arriving during tick T are delivered to the rx callback in order (the callback
   drops foreign types, other version bytes, and everything once the queue holds
   ``firmware.RXQ_CAPACITY`` messages; the queue is empty at the start of each delivery because the
   previous ``loop()`` drained it).

So the events of sim period k (tick t within it; period 0 is the one ``SwarmEnv.reset`` listens
to) are delivered at T = k·P + t and observed by the control step at T = (k+1)·P, whose commands
drive sim period k+1: the simulator's timing. Loops run over control periods; everything
inside is vectorised over robots (and over the ticks of a period).

The receive rules are not re-implemented: :func:`sim.events.summarise` applies them to the
messages the queue accepted, so the host test proves the C follows the simulator's definition.

The observation is the world's layout (``WorldConfig.obs_features``): each feature's firmware block
(``firmware_templates/features/<name>.c.j2``) has its twin in :data:`INT_FEATURES`. The emitter (the task's
transmitting robot, whose role's C is the task's partial, ``firmware_templates/tasks/``) is emulated by what it
does: it never moves, sends its role bit (and, with ``object_light``, its held light reading) and shows
:data:`~export.contract.firmware.LED_EMITTER`. In a world without an emitter no robot is one, the role bit is
ignored (every message is a neighbour's), the message never carries a flag and the LED stays off.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterable

import numpy as np

from kiloforge import numfmt
from kiloforge.actors.base import QuantizedActor
from kiloforge.xorshift import rng_seed, top_byte, xorshift32
from sim.config import ROLE_TARGET, WorldConfig
from sim.events import HeardEvents, PeriodSummary, summarise
from sim.features import emitter_sends_light, feature
from sim.light import ADC_MAX
from sim.motion import MODE_LEFT, MODE_RIGHT, MODE_STOP, MODE_STRAIGHT, schedule
from sim.table_features import NeighbourTable

from ..contract import firmware as fw
from ..contract.crc import crc16_rows
from ..contract.firmware import EVENT_DTYPE, MSG_BYTES, TICK_RECORD_BYTES


def n_control_steps(n_ticks: int, period_ticks: int) -> int:
    """Control steps in ``n_ticks`` ticks: at T = k * period_ticks < n_ticks, k >= 1.

    >>> n_control_steps(31, 31), n_control_steps(32, 31), n_control_steps(93, 31)
    (0, 1, 2)
    """
    return max(int(n_ticks) - 1, 0) // int(period_ticks)


@dataclass
class FirmwareInputs:
    """Everything a run of R robots for ``n_ticks`` kilo_ticks receives from the outside world."""

    uids: np.ndarray  #: (R,) uint16 kilo_uid of each robot
    calib: np.ndarray  #: (R, 4) uint8 kilo_straight_left, kilo_straight_right, kilo_turn_left, kilo_turn_right
    light: np.ndarray  #: (R, n_steps) int16 get_ambientlight() at control ticks P, 2P, ... (-1 = busy)
    events: np.ndarray  #: (N,) firmware.EVENT_DTYPE; per (robot, tick) in delivery order
    n_ticks: int

    def __post_init__(self) -> None:
        self.uids = np.asarray(self.uids, np.uint16)
        R = self.uids.shape[0]
        self.calib = np.asarray(self.calib, np.uint8)
        self.light = np.asarray(self.light, np.int16)
        assert self.uids.ndim == 1 and R >= 1, "uids must be a non-empty 1-D array"
        assert self.calib.shape == (R, 4), f"calib must be (R, 4) = ({R}, 4), got {self.calib.shape}"
        assert self.light.ndim == 2 and self.light.shape[0] == R, f"light must be (R, n_steps), got {self.light.shape}"
        assert self.events.dtype == EVENT_DTYPE, f"events must have dtype firmware.EVENT_DTYPE, got {self.events.dtype}"
        assert self.n_ticks >= 1, f"n_ticks must be >= 1, got {self.n_ticks}"
        if self.events.size:
            assert int(self.events["robot"].max()) < R, "an event names a robot >= R"
            assert int(self.events["tick"].max()) < self.n_ticks, "an event arrives after the last tick"

    @property
    def n_robots(self) -> int:
        return int(self.uids.shape[0])

    def n_steps(self, period_ticks: int) -> int:
        """Control steps in the run, at ticks k * period_ticks < n_ticks with k >= 1."""
        return n_control_steps(self.n_ticks, period_ticks)


@dataclass
class FirmwareOutputs:
    """What the firmware did, byte for byte (the layouts of :mod:`export.contract.firmware`)."""

    ticks: np.ndarray  #: (R, n_ticks, 16) uint8: left, right, spinup, LED, message_t bytes
    steps: np.ndarray  #: (R, n_steps, 2 + obs_dim) uint8: q_left, q_right, obs (int8 bytes); emitters 0

    @property
    def duties(self) -> np.ndarray:
        """(R, n_ticks, 2) uint8 set_motors values."""
        return self.ticks[..., 0:2]

    @property
    def spinup(self) -> np.ndarray:
        """(R, n_ticks) uint8: spinup_motors() called during the tick."""
        return self.ticks[..., 2]

    @property
    def led(self) -> np.ndarray:
        """(R, n_ticks) uint8 set_color byte."""
        return self.ticks[..., 3]

    @property
    def messages(self) -> np.ndarray:
        """(R, n_ticks, 12) uint8 outgoing message_t."""
        return self.ticks[..., 4:4 + MSG_BYTES]

    @property
    def commands(self) -> np.ndarray:
        """(R, n_steps, 2) uint8 motor commands (q_left, q_right) of each control step."""
        return self.steps[..., :2]

    @property
    def obs(self) -> np.ndarray:
        """(R, n_steps, obs_dim) int8 observation of each control step."""
        return self.steps[..., 2:].view(np.int8)


# --- the observation features' integer blocks (twins of firmware_templates/features/<name>.c.j2) ---------
def _int_wall(emu: "FirmwareEmulator", summ: PeriodSummary) -> np.ndarray:
    """wall.c.j2: the flag (already updated from this step's light reading) as KF_ONE / 0."""
    return np.where(emu.wall, int(emu.qp.one_q), 0)[:, None]


def _int_light(emu: "FirmwareEmulator", summ: PeriodSummary) -> np.ndarray:
    """light.c.j2: the held level and its change (already updated from this step's reading)."""
    return emu.light_obs


def _int_target(emu: "FirmwareEmulator", summ: PeriodSummary) -> np.ndarray:
    """target.c.j2: TGT[min(d, TGT_LAST)] (the full table: the same entries) when heard, else -KF_ONE."""
    R, one = emu.R, int(emu.qp.one_q)
    d = summ.target_dist_mm[0, :R].astype(np.int64)
    return np.where(summ.target_heard[0, :R], np.asarray(emu.qp.target_table, np.int64)[d], -one)[:, None]


def _int_object_light(emu: "FirmwareEmulator", summ: PeriodSummary) -> np.ndarray:
    """object_light.c.j2: the held emitter reading's level (L · KF_ONE) >> 10 (kept when an emitter message carrying
    L <= 1023 is heard, in kf_hear), else -KF_ONE before any."""
    return np.where(emu.obj_valid, emu.obj_level, -int(emu.qp.one_q))[:, None]


def _int_nbr_sensing(emu: "FirmwareEmulator", summ: PeriodSummary) -> np.ndarray:
    """nbr_sensing.c.j2: KF_ONE when any table entry's latest flag is set."""
    nbr = np.zeros(emu.R, np.int64)
    np.maximum.at(nbr, summ.table_rx.astype(np.int64), summ.table_flag.astype(np.int64))
    return np.where(nbr > 0, int(emu.qp.one_q), 0)[:, None]


def _int_rbf(emu: "FirmwareEmulator", summ: PeriodSummary) -> np.ndarray:
    """rbf.c.j2: per bin the table entries' RBF entries summed, saturated to int8."""
    rbf = np.zeros((emu.R, emu.world.n_rbf), np.int64)
    t_rx, t_d = summ.table_rx.astype(np.int64), summ.table_dist_mm.astype(np.int64)
    np.add.at(rbf, t_rx, np.asarray(emu.qp.rbf_table, np.int64)[:, t_d].T)  # (K, n_rbf) per table entry
    return np.minimum(rbf, numfmt.INT8_MAX)


def _int_random(emu: "FirmwareEmulator", summ: PeriodSummary) -> np.ndarray:
    """random.c.j2: the signed top byte b of the word (already stepped this control step) as (b · KF_ONE) >> 7."""
    return ((top_byte(emu.rand_word) * int(emu.qp.one_q)) >> 7)[:, None]


def host_rand_hard(uids: np.ndarray) -> np.ndarray:
    """(R,) the byte rand_hard() returns in setup() under the host build's kilolib stand-in
    (firmware_templates/host/kilolib_host.c: its 8-bit xorshift (7, 5, 3), state ``(uid ^ 0xA5) | 1``)."""
    x = (np.asarray(uids, np.int64) ^ 0xA5) & 0xFF | 1
    x ^= (x << 7) & 0xFF
    x ^= x >> 5
    x ^= (x << 3) & 0xFF
    return x.astype(np.uint8)


#: each observation feature's integer twin: (emulator, the period's summary) -> (R, width) int64
INT_FEATURES: dict[str, Callable[["FirmwareEmulator", PeriodSummary], np.ndarray]] = {
    "wall": _int_wall, "light": _int_light, "target": _int_target, "object_light": _int_object_light,
    "nbr_sensing": _int_nbr_sensing, "rbf": _int_rbf, "random": _int_random}


def int_feature(name: str) -> Callable[["FirmwareEmulator", PeriodSummary], np.ndarray]:
    """The integer twin of feature ``name``: a built-in's, or a task's own (its ``integer`` on the period's table)."""
    if name in INT_FEATURES:
        return INT_FEATURES[name]
    tf = feature(name).table

    def twin(emu: "FirmwareEmulator", summ: PeriodSummary) -> np.ndarray:
        table = NeighbourTable.of(summ.table_rx, summ.table_dist_mm, emu.R)
        return tf.int_values(table, int(emu.qp.one_q))

    return twin


def message_bytes(uids: np.ndarray, info: np.ndarray, msg_type: int, light: np.ndarray | None = None) -> np.ndarray:
    """(R, 12) uint8 message_t of each robot: version, uid LE, info, zeros (``light`` (R,): the emitter's held reading
    at data[MSG_LIGHT_BYTE], little-endian), type, CRC LE.

    >>> message_bytes(np.array([0x0102]), np.array([1]), 0x2A).tolist()
    [[1, 2, 1, 1, 0, 0, 0, 0, 0, 42, 104, 187]]
    """
    uids = np.asarray(uids, np.uint16)
    m = np.zeros((uids.shape[0], MSG_BYTES), np.uint8)
    m[:, 0] = fw.MSG_VERSION
    m[:, 1] = uids & 0xFF
    m[:, 2] = uids >> 8
    m[:, fw.MSG_INFO_BYTE] = np.asarray(info, np.uint8)
    if light is not None:
        m[:, fw.MSG_LIGHT_BYTE] = np.asarray(light, np.int64) & 0xFF
        m[:, fw.MSG_LIGHT_BYTE + 1] = (np.asarray(light, np.int64) >> 8) & 0xFF
    m[:, fw.MSG_TYPE_BYTE] = msg_type
    crc = crc16_rows(m[:, :fw.MSG_CRC_BYTES])  # (R,)
    m[:, fw.MSG_CRC_BYTES] = crc & 0xFF
    m[:, fw.MSG_CRC_BYTES + 1] = crc >> 8
    return m


class FirmwareEmulator:
    """The generated program on R robots at once (see the module doc for the tick model).

    Use :meth:`run` for a whole recorded stream, or drive it period by period (firmware in the
    loop): ``tick_outputs(P)`` and ``deliver(events)`` for the listening period 0, then per period
    ``control_step(light)`` at its control tick, ``tick_outputs(n)`` for its ticks and
    ``deliver(events)`` with the messages that arrive during it.
    """

    def __init__(self, qp: QuantizedActor, uids: Iterable[int], calib: np.ndarray | None = None, *,
                 emitter_uids: Iterable[int] | None = None, msg_type: int = fw.DEFAULT_MSG_TYPE,
                 rxq_capacity: int = fw.RXQ_CAPACITY, rand_hard: np.ndarray | None = None) -> None:
        self.qp = qp
        self.world: WorldConfig = qp.world
        self.P = int(self.world.period_ticks)
        self.uids = np.asarray(list(uids) if not isinstance(uids, np.ndarray) else uids, np.uint16)
        R = self.uids.shape[0]
        assert self.uids.ndim == 1 and R >= 1, "need at least one robot uid"
        self.R = R
        calib = np.tile(np.asarray(fw.DEFAULT_CALIB, np.uint8), (R, 1)) if calib is None else calib
        self.calib = np.asarray(calib, np.uint8)
        # each robot's rand_hard() byte in setup() (the random feature's seed); default: the host build's
        self.rand_hard = host_rand_hard(self.uids) if rand_hard is None else np.asarray(rand_hard, np.uint8)
        assert self.calib.shape == (R, 4), f"calib must be (R, 4), got {self.calib.shape}"
        roles = self.world.has_roles
        emitters = (self.world.emitter_uid,) if emitter_uids is None else tuple(int(u) for u in emitter_uids)
        assert roles or emitter_uids is None, "emitter uids in a world without an emitter"
        self.is_emitter = np.isin(self.uids.astype(np.int64), np.asarray(emitters, np.int64)) & roles  # (R,)
        self.msg_type = fw.check_msg_type(msg_type)
        assert rxq_capacity >= 1, "the rx queue holds at least one message"
        self.rxq_capacity = int(rxq_capacity)
        # duties of each motor mode: (R, 4 modes, 2)
        self.mode_duty = np.zeros((R, 4, 2), np.uint8)
        self.mode_duty[:, MODE_STRAIGHT] = self.calib[:, 0:2]
        self.mode_duty[:, MODE_LEFT, 0] = self.calib[:, 2]
        self.mode_duty[:, MODE_RIGHT, 1] = self.calib[:, 3]
        self.mode_duty[:, MODE_STOP] = 0
        # the messages a searcher can send (sensing 0 / 1) and the emitter's
        self.msg_searcher = np.stack([message_bytes(self.uids, np.zeros(R, np.uint8), self.msg_type),
                                      message_bytes(self.uids, np.full(R, fw.SENSING_BIT, np.uint8),
                                                    self.msg_type)], 1)  # (R, 2, 12)
        self.sends_light = emitter_sends_light(self.world)
        self.msg_emitter = self._emitter_message(np.full(R, fw.LIGHT_NONE))
        # each observed feature's inputs and its integer twin, in the world's order
        self._int_features = [(self.world.obs_slice(n), int_feature(n)) for n in self.world.features]
        self.led_codes = {name: fw.rgb(*c) for name, c in (
            ("off", fw.LED_OFF), ("emitter", fw.LED_EMITTER), ("sensing", fw.LED_SENSING),
            ("nbr", fw.LED_NBR_SENSING))}
        self.reset()

    def _emitter_message(self, light: np.ndarray) -> np.ndarray:
        """(R, 12) the emitter role's message: role bit, and its held light reading where the world's layout reads it."""
        return message_bytes(self.uids, np.full(self.R, fw.ROLE_BIT, np.uint8), self.msg_type,
                             light if self.sends_light else None)

    # --- state ------------------------------------------------------------------------------
    def reset(self) -> None:
        """What setup() does: forget everything; the next control step starts a new history."""
        R = self.R
        self.steps_done = 0
        self.wall = np.zeros(R, bool)
        self.light_level = np.zeros(R, np.int64)  # light.c.j2's held level and whether one is held
        self.light_valid = np.zeros(R, bool)
        self.light_obs = np.zeros((R, 2), np.int64)
        self.rand_word = rng_seed(self.uids, self.rand_hard)  # random.c.j2's word as setup() seeds it
        self.obj_level = np.zeros(R, np.int64)  # object_light.c.j2's held level and whether one is held
        self.obj_valid = np.zeros(R, bool)
        self.emitter_light = np.full(R, fw.LIGHT_NONE, np.int64)  # an emitter's held reading (sent in its message)
        self.msg_emitter = self._emitter_message(self.emitter_light)
        self.q = np.zeros((R, 2), np.uint8)
        self.state = self.qp.setup_state(self.uids)  # the actor's state as setup() leaves it
        self.duty = np.zeros((R, 2), np.uint8)  # set_motors(0, 0) in setup
        self.turn = np.zeros(R, np.uint8)
        self.turn_mode = np.full(R, MODE_STOP, np.uint8)
        self.straight = np.zeros(R, np.uint8)
        self.led = np.where(self.is_emitter, self.led_codes["emitter"], self.led_codes["off"]).astype(np.uint8)
        self.msg = np.where(self.is_emitter[:, None], self.msg_emitter, self.msg_searcher[:, 0])  # (R, 12)
        self._heard: list[np.ndarray] = []  # accepted events of the current period, arrival order

    # --- receiving ----------------------------------------------------------------------------
    def accepted(self, events: np.ndarray) -> np.ndarray:
        """The events the rx callback queues, in arrival order (filter, then the queue capacity)."""
        ev = np.asarray(events)
        assert ev.dtype == EVENT_DTYPE, f"events must have dtype firmware.EVENT_DTYPE, got {ev.dtype}"
        if ev.size == 0:
            return ev
        ev = ev[np.lexsort((ev["tick"], ev["robot"]))]  # by (robot, tick), ties in given order
        ours = (ev["type"] == self.msg_type) & (ev["version"] == fw.MSG_VERSION) & ~self.is_emitter[ev["robot"]]
        ev = ev[ours]
        key = ev["robot"].astype(np.int64) << 32 | ev["tick"].astype(np.int64)  # (N,) non-decreasing
        start = np.r_[0, np.flatnonzero(np.diff(key)) + 1] if key.size else np.zeros(0, np.int64)
        run = np.diff(np.r_[start, key.size])
        rank = np.arange(key.size) - np.repeat(start, run)  # position within its tick's delivery
        return ev[rank < self.rxq_capacity]

    def deliver(self, events: np.ndarray) -> None:
        """Messages arriving during the current period (after its control step, before the next)."""
        acc = self.accepted(events)
        if acc.size:
            self._heard.append(acc)

    def _summary(self):
        heard = np.concatenate(self._heard) if self._heard else np.zeros(0, EVENT_DTYPE)
        heard = heard[np.lexsort((heard["tick"], heard["robot"]))]  # arrival order per robot
        uids, sender = np.unique(heard["uid"], return_inverse=True)
        M = max(self.R, uids.size)
        z = np.zeros(heard.size, np.int32)
        ev = HeardEvents(env=z, rx=heard["robot"].astype(np.int32), sender=sender.astype(np.int32).reshape(-1),
                         tick=(heard["tick"] % self.P).astype(np.int16),  # one period's events
                         dist_mm=heard["dist"].astype(np.float64),
                         role=np.where(heard["role"] & int(self.world.has_roles), ROLE_TARGET, 0).astype(np.uint8),
                         flag=(heard["flag"] & 1).astype(np.uint8),
                         light=np.where(heard["light"] <= ADC_MAX, heard["light"].astype(np.int64), -1))
        return summarise(ev, self.world, 1, M)

    # --- the control step ---------------------------------------------------------------------
    def control_step(self, light: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Run the control step of every robot at its control tick; returns (q (R, 2) uint8, obs (R, D) int8).

        ``light`` (R,) int: get_ambientlight() now. Emitters return zeros (they run no policy).
        """
        qp, R = self.qp, self.R
        light = np.asarray(light, np.int64)
        assert light.shape == (R,), f"light must be ({R},), got {light.shape}"
        summ = self._summary()
        self._heard = []
        w = self.world
        target_heard = summ.target_heard[0, :R]  # (R,)

        if w.has_feature("wall"):
            self.wall = np.where(light >= 0, light >= w.light_threshold, self.wall)
        if w.has_feature("light"):
            ok = light >= 0
            now = (np.maximum(light, 0) * int(qp.one_q)) >> 10
            change = np.where(ok & self.light_valid, now - self.light_level, 0)
            self.light_level = np.where(ok, now, self.light_level)
            self.light_valid |= ok
            self.light_obs = np.stack([self.light_level, change], 1)
        if w.has_feature("random"):
            self.rand_word = xorshift32(self.rand_word)
        if w.has_feature("object_light"):
            lit = summ.target_light[0, :R]  # (R,) the period's latest emitter reading heard (-1: none)
            self.obj_level = np.where(lit >= 0, (np.maximum(lit, 0) * int(qp.one_q)) >> 10, self.obj_level)
            self.obj_valid |= lit >= 0
        if self.sends_light:  # an emitter reads the light at its control tick and sends its held reading
            self.emitter_light = np.where(light >= 0, light, self.emitter_light)
            self.msg_emitter = self._emitter_message(self.emitter_light)
        obs = np.zeros((R, w.obs_dim), np.int64)
        for inputs, twin in self._int_features:
            obs[:, inputs] = twin(self, summ)

        act = np.asarray(qp.action_table, np.int64)[self.q.astype(np.int64)]  # (R, 2) ACT[previous q], a_0 = ACT[0] = 0
        q, self.state = qp.step_int(np.concatenate([act, obs], 1), self.state)  # (R, 2) uint8
        self.steps_done += 1

        searcher = ~self.is_emitter
        self.q = np.where(searcher[:, None], q, 0).astype(np.uint8)
        turn, mode, straight = schedule(self.q[:, 0], self.q[:, 1], self.P)
        self.turn = np.where(searcher, turn, 0).astype(np.uint8)
        self.turn_mode = mode
        self.straight = np.where(searcher, straight, 0).astype(np.uint8)
        sensing = target_heard & searcher
        nbr = obs[:, w.obs_index("nbr_sensing")] != 0 if w.has_feature("nbr_sensing") else np.zeros(R, bool)
        led = np.where(sensing, self.led_codes["sensing"],
                       np.where(nbr, self.led_codes["nbr"], self.led_codes["off"]))
        self.led = np.where(self.is_emitter, self.led_codes["emitter"], led).astype(np.uint8)
        self.msg = np.where(self.is_emitter[:, None], self.msg_emitter,
                            self.msg_searcher[np.arange(R), sensing.astype(np.int64)])
        obs8 = np.where(searcher[:, None], obs, 0).astype(np.int8)
        return self.q.copy(), obs8

    def tick_outputs(self, n: int) -> np.ndarray:
        """(R, n, 16) uint8 records of the first ``n`` (<= period) ticks after a control step."""
        assert 1 <= n <= self.P, f"a period has 1..{self.P} ticks, asked for {n}"
        R = self.R
        t = np.arange(n)[None, :]  # (1, n)
        turn = self.turn.astype(np.int64)[:, None]
        end = turn + self.straight.astype(np.int64)[:, None]
        mode = np.where(t < turn, self.turn_mode[:, None], np.where(t < end, MODE_STRAIGHT, MODE_STOP))  # (R, n)
        duty = self.mode_duty[np.arange(R)[:, None], mode]  # (R, n, 2)
        prev = np.concatenate([self.duty[:, None], duty[:, :-1]], 1)  # (R, n, 2) duty of the tick before
        spin = ((duty != 0) & (prev == 0)).any(-1)  # a motor starts from rest
        self.duty = duty[:, -1].copy()
        out = np.empty((R, n, TICK_RECORD_BYTES), np.uint8)
        out[..., 0:2] = duty
        out[..., 2] = spin
        out[..., 3] = self.led[:, None]
        out[..., 4:] = self.msg[:, None, :]
        return out

    # --- a whole recorded stream ----------------------------------------------------------------
    def run(self, inputs: FirmwareInputs) -> FirmwareOutputs:
        """Replay ``inputs`` from setup(); every output byte of every tick and control step."""
        assert inputs.n_robots == self.R and np.array_equal(inputs.uids, self.uids), "inputs are for other robots"
        assert np.array_equal(inputs.calib, self.calib), "inputs carry other calibration values"
        P, R = self.P, self.R
        n_steps = inputs.n_steps(P)
        assert inputs.light.shape == (R, n_steps), f"light must be (R, {n_steps}), got {inputs.light.shape}"
        self.reset()
        T = inputs.n_ticks
        ev = inputs.events[np.argsort(inputs.events["tick"], kind="stable")]
        bounds = np.searchsorted(ev["tick"], np.arange(n_steps + 2) * P)  # period k: bounds[k]..bounds[k+1]
        ticks = np.empty((R, T, TICK_RECORD_BYTES), np.uint8)
        steps = np.zeros((R, n_steps, 2 + self.world.obs_dim), np.uint8)
        for k in range(n_steps + 1):  # period 0 listens, period k >= 1 starts with control step k
            if k:
                q, obs = self.control_step(inputs.light[:, k - 1])
                steps[:, k - 1, :2] = q
                steps[:, k - 1, 2:] = obs.view(np.uint8)
            n = min(P, T - k * P)
            ticks[:, k * P:k * P + n] = self.tick_outputs(n)
            self.deliver(ev[bounds[k]:bounds[k + 1]])
        return FirmwareOutputs(ticks=ticks, steps=steps)


def events_from_sim(events: HeardEvents, period: int, cfg: WorldConfig, n_robots: int,
                    msg_type: int = fw.DEFAULT_MSG_TYPE) -> np.ndarray:
    """Simulator events of control period ``period`` -> the firmware's event stream (EVENT_DTYPE).

    Receiver ``robot = env * n_robots + rx``; searcher i sends kilo_uid i + 1, the target
    the emitter's uid (the world's); distances become the uint8 mm estimate_distance() reports
    (numfmt.distance_u8); ticks become global (``period * period_ticks + tick``). Returned in
    arrival order per receiver (the order :func:`sim.events.summarise` uses).
    """
    n = len(events)
    out = np.zeros(n, EVENT_DTYPE)
    out["robot"] = events.env.astype(np.int64) * n_robots + events.rx
    out["tick"] = int(period) * cfg.period_ticks + events.tick.astype(np.int64)
    out["uid"] = np.where(events.sender < 0, cfg.emitter_uid, events.sender.astype(np.int64) + 1)
    out["role"] = events.role
    out["flag"] = events.flag
    out["type"] = fw.check_msg_type(msg_type)
    out["version"] = fw.MSG_VERSION
    out["dist"] = numfmt.distance_u8(events.dist_mm)
    if events.light is not None:  # the emitter's reading in its messages (LIGHT_NONE before its first); 0 in others
        out["light"] = np.where(events.role == ROLE_TARGET, np.where(events.light >= 0, events.light, fw.LIGHT_NONE), 0)
    return out[np.lexsort((out["tick"], out["robot"]))]
