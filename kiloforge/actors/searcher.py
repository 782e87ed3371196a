"""Actor kind ``"searcher"``: the hand-written run-and-tumble searcher of :mod:`sim.baselines` as firmware.

The float actor is :class:`sim.baselines.HandWrittenSearcher` itself; its artifact holds no arrays,
only the :class:`~sim.baselines.SearcherParams` in the meta (``params``: every field, ints as ints,
floats as JSON floats, so a file reads back to exactly the searcher it was written from). The
shipped ones are ``export/data/searcher_policy.npz`` (``TUNED["kilobot"]`` in ``preset("kilobot")``) and
``export/data/pusher_policy.npz`` (the same with :data:`sim.baselines.PUSHER`), so ``python -m export --policy
searcher`` (or ``pusher``) renders them. When the preset or the tuned parameters change, rewrite them with
``python -m tools.ship_rules`` (tests/test_searcher_firmware.py fails on a stale file).

The integer searcher (:meth:`QuantizedSearcher.step_int`, rendered by
``firmware_templates/actors/searcher.c.j2``) runs the float searcher's rules in the same order on
the int8 observation every firmware builds (wall, target, neighbour flag and RBF histogram at
``e_in``; the action part of the tuple is ignored) and a few bytes of state. What changes:

* **observations**: ``wall = 2 obs_wall > ONE``, ``heard = obs_target >= 0``, ``nbr = 2 obs_nbr > ONE``
  (the float ``> 0.5`` on values 0 / 1); the stop rule ``tdist <= stop_dist`` is
  ``obs_target <= STOP_Q = floor(stop_dist * 2**e_in)``, exact on quantised distances (so is the pusher's
  "pushed out" rule ``obs_target > STOP_Q``, and its margin: the distance grew by more than ``push_margin``
  exactly when ``-obs_target < best - MARGIN_Q``, ``MARGIN_Q = floor(push_margin * 2**e_in)``); the neighbour
  proximity ``Σ_k rbf_k (n - k) / n`` is ``Σ_k obs_rbf_k (n - k)`` in int32 (the float one times
  ``n * 2**e_in``, so every comparison of two scores agrees). The only differences from the float
  searcher are those of the observation's quantisation (1/64 of the comm radius at ``e_in = 6``).
* **counters** saturate where the float ones run on without changing a decision: ``wall_cool``
  stops at 0 and ``run_left`` at -1 (only ``<= 0`` and ``max(run_left, cooldown >= 0)`` read them),
  ``fails`` and ``miss`` at 255 (compared with thresholds <= 254). "Run forever" is ``BIG = 2**20``
  periods, as in the float searcher.
* **randomness**: no NumPy generator on a robot. Each robot owns the xorshift32 word of
  :mod:`kiloforge.actors.rules` seeded from its ``kilo_uid``, stepped once every control period whether
  its draws are used or not (as the float searcher draws every period). Its four bytes are the period's draws: byte 0 the turn direction
  (left when < 128), byte 1 the tumble ``1 + (b * tumble_max >> 8)``, byte 2 the wall turn
  ``wall_turn_min + (b * span >> 8)``, byte 3 the run length ``RUN[b]``, a 256-entry table of
  :func:`sim.baselines.run_lengths` at ``u = (b + 0.5) / 256``. So each uniform integer has
  probabilities within 1/256 of the float's, and the run-length CDF is within 1/512 of the float's
  (tests/test_searcher_firmware.py).

:class:`FirmwareDrawSearcher` is the float searcher taking its draws from these bytes: fed the
dequantised observations it gives exactly the integer searcher's commands (the test of the integer
reference), and the error report compares it on recorded float observations with the integer
searcher on the quantised ones.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping

import numpy as np

from sim.baselines import COUNTER_MAX, TUNED, HandWrittenSearcher, SearcherParams, make_policy, run_lengths
from sim.config import ACTION_DIM, WorldConfig
from sim.motion import action_to_u8
from sim.tasks.base import TaskRef

from .. import numfmt
from ..artifact import plain_provenance
from ..errors import QuantizeError
from .base import (BudgetItem, BudgetOption, BudgetSpec, CDefine, CTable, FloatPolicy, QuantizedActor, RenderSpec,
                   check_world_and_task, invalid, sensing_tables)
from .rules import (SEED_ADD, SEED_MUL, OwnSeeds, RuleActor, RuleKind, UidStreams, draw_bytes, params_from_meta, rng_seed,
                    xorshift32)

BIG = 1 << 20  #: "run until something happens" (periods), as in sim.baselines
RUN_TABLE_SIZE = 256  #: one entry per value of the run-length draw byte
COUNT_MAX = COUNTER_MAX  #: fails and miss saturate here (uint8)
STATE_BYTES = 4 + 4 + 4 + 4 + 7  #: rng, run_left, prev_score, best (uint32/int32) + seven uint8 counters and flags
#: SearcherParams fields newer than the first searcher artifacts, with the values that keep those files' rules
LATER_FIELDS = {"push_margin": 0.0, "hold_within": False}


# --------------------------------------------------------------------------------------------
# The float searcher and its random draws
# --------------------------------------------------------------------------------------------
class SeededSearcher(OwnSeeds, HandWrittenSearcher):
    """The float searcher; ``reset`` without a generator takes the next child of its own seed sequence."""


def run_table(p: SearcherParams) -> np.ndarray:
    """(256,) uint16 run lengths RUN[b] = run_lengths(p, (b + 0.5) / 256)."""
    return run_lengths(p, (np.arange(RUN_TABLE_SIZE) + 0.5) / RUN_TABLE_SIZE).astype(np.uint16)


def firmware_draws(p: SearcherParams, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The draws of :meth:`sim.baselines.HandWrittenSearcher.draws` from the firmware's bytes (..., 4)."""
    b = np.asarray(b, np.int64)
    dirs = np.where(b[..., 0] < 128, 1, -1).astype(np.int8)
    tumble = 1 + ((b[..., 1] * p.tumble_max_steps) >> 8)
    wall = p.wall_turn_min + ((b[..., 2] * (p.wall_turn_max - p.wall_turn_min + 1)) >> 8)
    return dirs, tumble, wall, run_lengths(p, (b[..., 3] + 0.5) / RUN_TABLE_SIZE)


class FirmwareDrawSearcher(UidStreams, HandWrittenSearcher):
    """The float searcher drawing from the firmware's xorshift32 streams (one per robot, seeded by uid)."""

    def draws(self, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        self.word = xorshift32(self.word)
        return firmware_draws(self.p, draw_bytes(self.word))


# --------------------------------------------------------------------------------------------
# The float policy (the artifact)
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class SearcherPolicy(FloatPolicy):
    """The hand-written searcher with its parameters in a world; no arrays."""

    kind: ClassVar[str] = "searcher"
    params: SearcherParams
    world: WorldConfig
    provenance: dict[str, Any] = field(default_factory=dict)
    task: TaskRef | None = None  #: the task it was trained for (None: a file from before tasks)

    def __post_init__(self) -> None:
        check_world_and_task(self.world, self.task)
        if not isinstance(self.params, SearcherParams):
            invalid(f"params must be SearcherParams, got {type(self.params).__name__}")
        object.__setattr__(self, "provenance", plain_provenance(self.provenance))

    @property
    def layer_sizes(self) -> list[int]:
        """[tuple width, 2]: no layers, the rules read one tuple."""
        return [self.world.tuple_dim, ACTION_DIM]

    def describe(self) -> str:
        p = self.params
        return (f"hand-written searcher (run and tumble; run {p.run_min_steps:g}..{p.run_max_steps} periods, "
                f"alpha {p.run_alpha:g}, stop at {p.stop_dist:g} comm radius)")

    def arrays(self) -> dict[str, np.ndarray]:
        return {}

    def kind_meta(self) -> dict[str, Any]:
        """Every parameter, except a :data:`LATER_FIELDS` one at its old value (older files read back alike)."""
        d = dataclasses.asdict(self.params)
        return {"params": {k: v for k, v in d.items() if k not in LATER_FIELDS or v != LATER_FIELDS[k]}}

    def initial_state(self, n: int) -> SeededSearcher:
        """A float searcher of n robots (its counters and its own generator, seed 0)."""
        s = SeededSearcher(self.world, self.params)
        s.reset(1, n)
        return s

    def step(self, x: np.ndarray, state: SeededSearcher) -> tuple[np.ndarray, SeededSearcher]:
        """Tuples (n, D) -> the searcher's commands on their observation part (the state is updated in place)."""
        obs = np.asarray(x, np.float64)[:, ACTION_DIM:]
        return state.act(obs[None])[0], state


def params_of(meta_params: Any) -> SearcherParams:
    """SearcherParams of an artifact's ``params`` (every field, of its type and in its range, checked by
    SearcherParams; a field added after the file was written, :data:`LATER_FIELDS`, reads as its default);
    raises PolicyError."""
    return params_from_meta(SearcherParams, meta_params, LATER_FIELDS)


def pusher_policy(world: WorldConfig) -> SearcherPolicy:
    """The pusher artifact for ``world``: its tuned searcher with :data:`sim.baselines.PUSHER`."""
    notes = f"sim.baselines.HandWrittenSearcher, TUNED parameters of '{world.name}' with sim.baselines.PUSHER"
    return searcher_policy(world, make_policy("pusher", world).p, {"notes": notes})


def searcher_policy(world: WorldConfig, params: SearcherParams | None = None,
                    provenance: Mapping[str, Any] | None = None) -> SearcherPolicy:
    """The searcher artifact for ``world`` (default parameters: ``TUNED[world.name]``, else the defaults)."""
    p = params if params is not None else TUNED.get(world.name, SearcherParams())
    return SearcherPolicy(p, world, dict(provenance or {"notes": f"sim.baselines.HandWrittenSearcher, "
                                                                  f"TUNED parameters of '{world.name}'"}))


# --------------------------------------------------------------------------------------------
# The integer searcher
# --------------------------------------------------------------------------------------------
@dataclass
class SearcherState:
    """Per robot (R,): the firmware's searcher fields."""

    rng: np.ndarray  #: uint32 xorshift32 word
    turn_left: np.ndarray  #: pivot periods still to do
    turn_dir: np.ndarray  #: 1 left (counter-clockwise), 0 right
    run_left: np.ndarray  #: straight periods still to do, -1..BIG
    wall_cool: np.ndarray  #: periods the wall flag is still ignored, >= 0
    prev_level: np.ndarray
    prev_score: np.ndarray
    best: np.ndarray  #: best target score since the last turn (push_margin)
    fails: np.ndarray
    settled: np.ndarray
    miss: np.ndarray


@dataclass(frozen=True, eq=False, kw_only=True)
class QuantizedSearcher(RuleActor, QuantizedActor):
    """The integer searcher (module doc): the float parameters and their firmware constants."""

    kind: ClassVar[str] = "searcher"
    params: SearcherParams
    speed_q: int  #: uint8 command of both motors on a straight run (action_to_u8(speed))
    stop_q: int  #: stop once obs_target <= this (floor(stop_dist * 2**e_in))
    margin_q: int  #: push_margin in obs_target units, floor(push_margin * 2**e_in): worse once it grew by more
    run_table: np.ndarray  #: (256,) uint16, run_table(params)

    def __post_init__(self) -> None:
        super().__post_init__()
        assert 0 <= self.speed_q <= 255 and 0 <= self.stop_q <= numfmt.INT8_MAX, "speed_q / stop_q out of range"
        assert 0 <= self.margin_q <= numfmt.INT8_MAX, "margin_q out of range"
        assert self.run_table.shape == (RUN_TABLE_SIZE,) and self.run_table.dtype == np.uint16, "run_table shape/dtype"

    def setup_state(self, uids: np.ndarray) -> SearcherState:
        """What setup() leaves: every field 0, the generator seeded from kilo_uid."""
        R = np.asarray(uids).shape[0]
        z = np.zeros(R, np.int64)
        return SearcherState(rng=rng_seed(uids), turn_left=z, turn_dir=z, run_left=z, wall_cool=z, prev_level=z,
                             prev_score=z, best=z, fails=z, settled=z.astype(bool), miss=z)

    def step_int(self, x: np.ndarray, state: SearcherState) -> tuple[np.ndarray, SearcherState]:
        """int8 tuples (R, D) and the state -> (uint8 commands (R, 2), the new state); the float rules, in order."""
        p, one = self.params, int(self.one_q)
        x = np.asarray(x, np.int64)
        o = x[:, ACTION_DIM:]
        w = self.world
        n = w.n_rbf
        wall = 2 * o[:, w.obs_index("wall")] > one
        tq = o[:, w.obs_index("target")]
        heard = tq >= 0
        nbr = 2 * o[:, w.obs_index("nbr_sensing")] > one
        prox = o[:, w.obs_slice("rbf")] @ (n - np.arange(n))
        level = np.where(heard, 2, np.where(nbr, 1, 0))
        score = np.where(heard, -tq, prox)
        word = xorshift32(state.rng)
        dirs, tumble, wall_turn, _ = firmware_draws(p, draw_bytes(word))
        runs = self.run_table.astype(np.int64)[draw_bytes(word)[:, 3]]
        if p.turn_sign == 2:
            left = np.where(level == 2, state.turn_dir == 0, True)
        else:
            left = (dirs > 0) if p.turn_sign == 0 else np.full(dirs.shape, p.turn_sign > 0)

        turn_left, turn_dir, run_left = state.turn_left.copy(), state.turn_dir.copy(), state.run_left.copy()
        settled = state.settled
        miss = np.where(settled & ~heard, np.minimum(state.miss + 1, COUNT_MAX), 0)
        pushed_out = settled & heard & (tq > self.stop_q) & p.hold_within
        leave = settled & (miss >= p.settle_hold)
        holding = settled & ~leave
        level = np.where(holding, 2, level)
        holding = holding & ~pushed_out
        settled = holding
        turning = turn_left > 0
        same = (level == state.prev_level) & (level >= 1) & ~holding
        improved = same & (score > state.prev_score)
        worse = same & ~improved & ~turning
        if p.push_margin > 0:
            worse = np.where(same & (level == 2), ~turning & (score < state.best - self.margin_q), worse)
        entered = (level > state.prev_level) | pushed_out
        lost = (level < state.prev_level) | leave

        def start(mask, steps, run):
            nonlocal turn_left, turn_dir, run_left
            turn_left = np.where(mask, steps, turn_left)
            turn_dir = np.where(mask, left, turn_dir)
            run_left = np.where(mask, run, run_left)

        start((level == 0) & ~turning & (run_left <= 0), tumble, runs)
        grad = (level == 2) | ((level == 1) & p.nbr_gradient)
        start(grad & worse, tumble, BIG)
        run_left = np.where(grad & improved & ~turning, BIG, run_left)
        fails = np.where(level == 2, np.where(worse, np.minimum(state.fails + 1, COUNT_MAX), state.fails), 0)
        hit = wall & (state.wall_cool <= 0) & ~turning
        start(hit, wall_turn, np.maximum(run_left, p.wall_cooldown))
        wall_cool = np.where(hit, wall_turn + p.wall_cooldown, np.maximum(state.wall_cool - 1, 0))
        start(entered, 0, BIG)
        start(lost & ~entered, p.uturn_steps, runs)
        fails = np.where(lost | entered, 0, fails)
        settled = settled | ((level == 2) & heard & ((tq <= self.stop_q) | (fails >= p.settle_patience)))

        turn_now = (turn_left > 0) & ~settled
        straight = ~turn_now & ~settled
        q = np.zeros((x.shape[0], ACTION_DIM), np.uint8)
        q[:, 0] = np.where(turn_now, np.where(turn_dir > 0, 255, 0), np.where(straight, self.speed_q, 0))
        q[:, 1] = np.where(turn_now, np.where(turn_dir > 0, 0, 255), np.where(straight, self.speed_q, 0))
        new = SearcherState(rng=word, turn_left=np.where(turn_now, turn_left - 1, turn_left), turn_dir=turn_dir,
                            run_left=np.where(straight, np.maximum(run_left - 1, -1), run_left), wall_cool=wall_cool,
                            prev_level=level, prev_score=score,
                            best=np.where(same & ~turning & ~entered, np.maximum(state.best, score), score),
                            fails=fails,
                            settled=settled, miss=miss)
        return q, new

    def summary(self) -> dict[str, Any]:
        return {"kind": self.kind, "format": self.format_name, "rounding": self.rounding, "e_in": int(self.e_in),
                "params": dataclasses.asdict(self.params), "speed_q": int(self.speed_q), "stop_q": int(self.stop_q),
                "margin_q": int(self.margin_q),
                "run_table": {"min": int(self.run_table.min()), "max": int(self.run_table.max()),
                              "mean": float(self.run_table.mean())},
                "rng": "xorshift32 (13, 17, 5), seed kilo_uid * 0x9E3779B1 + 0x7F4A7C15",
                "policy_hash": self.policy_hash, "world": self.world.name}

    def describe(self) -> str:
        return (f"hand-written searcher: speed {self.speed_q}, stop at target obs <= {self.stop_q}, runs "
                f"{int(self.run_table.min())}..{int(self.run_table.max())}, e_in {self.e_in}")


def quantize_searcher(policy: SearcherPolicy, e_in: int | None = None) -> QuantizedSearcher:
    """The integer searcher of ``policy`` (every parameter fits its firmware field: SearcherParams checks
    :data:`sim.baselines.PARAM_RANGES`)."""
    p = policy.params
    e = numfmt.DEFAULT_INPUT_EXP if e_in is None else int(e_in)
    if not 0 <= e <= numfmt.DEFAULT_INPUT_EXP:
        raise QuantizeError(f"e_in must be in 0..{numfmt.DEFAULT_INPUT_EXP}, got {e}")
    stop_q = min(int(np.floor(p.stop_dist * (1 << e))), numfmt.INT8_MAX)
    margin_q = min(int(np.floor(p.push_margin * (1 << e))), numfmt.INT8_MAX)
    return QuantizedSearcher(params=p, speed_q=int(action_to_u8(np.array(p.speed))), stop_q=stop_q, margin_q=margin_q,
                             run_table=run_table(p), e_in=e, world=policy.world, policy_hash=policy.hash,
                             **sensing_tables(policy.world, e))


# --------------------------------------------------------------------------------------------
# The kind
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SearcherArch:
    """The searcher's size does not vary: a fixed state, the run-length table, the rules."""


#: code beside the base estimate: the rules and xorshift32 (~0.4 KB) minus the dense kernels the base counts
#: and this program leaves out; measured: avr-gcc 10,962 B flash for the kilobot searcher vs 14,315 B analytic
#: with a +700 B guess, so about -2.6 KB
CODE_B = -2_600


class SearcherKind(RuleKind):
    """The hand-written searcher of sim.baselines (the baseline to flash next to a learned policy)."""

    name: ClassVar[str] = "searcher"
    template: ClassVar[str] = "actors/searcher.c.j2"
    arch = SearcherArch
    budget_usage: ClassVar[str] = "--searcher PRESET"
    budget_options: ClassVar[tuple[BudgetOption, ...]] = (
        BudgetOption("--searcher", "the hand-written searcher (its size does not depend on its parameters)",
                     metavar="PRESET", positive=False, choices=tuple(TUNED)),
    )

    def policy_of(self, meta_params: Any, world: WorldConfig, provenance: dict[str, Any]) -> SearcherPolicy:
        return SearcherPolicy(params_of(meta_params), world, provenance)

    def swarm_policy(self, policy: SearcherPolicy, world: WorldConfig | None = None) -> SeededSearcher:
        """The float searcher of sim.baselines (its own generator unless reset gets one)."""
        return SeededSearcher(world or policy.world, policy.params)

    def quantize_rule(self, policy: SearcherPolicy, e_in: int | None) -> QuantizedSearcher:
        return quantize_searcher(policy, e_in)

    def draw_reference(self, policy: SearcherPolicy, uids: np.ndarray) -> FirmwareDrawSearcher:
        return FirmwareDrawSearcher(policy.world, policy.params, uids)

    def budget_spec(self, world: WorldConfig, arch: SearcherArch, e_in: int) -> BudgetSpec:
        return BudgetSpec(
            header="hand-written searcher (no dense layers)", layer_sizes=(world.tuple_dim, ACTION_DIM), dense=(),
            flash=(BudgetItem("flash", "run-length table", 2 * RUN_TABLE_SIZE, f"{RUN_TABLE_SIZE} x uint16"),),
            memory=(BudgetItem("sram", "searcher state", STATE_BYTES, "rng, run, score, best (4 B each) + 7 counters"),),
            scratch=(BudgetItem("sram", "tuple buffer", world.tuple_dim, f"{world.tuple_dim} int8"),),
            code_b=CODE_B, code_note="(the searcher's rules, without the dense kernels; estimate)")

    def render_spec(self, qp: QuantizedSearcher) -> RenderSpec:
        p = qp.params
        return RenderSpec(
            memory=(),
            scratch=(
                CDefine("KF_SPEED", qp.speed_q, comment="motor command of a straight run"),
                CDefine("KF_STOP_Q", qp.stop_q, comment=f"stop once the target obs <= this ({p.stop_dist:g} at e_in)"),
                CDefine("KF_TUMBLE_MAX", p.tumble_max_steps, comment="a tumble pivots 1..this many periods"),
                CDefine("KF_WALL_TURN_MIN", p.wall_turn_min, comment="a wall turn pivots min .. min + span - 1"),
                CDefine("KF_WALL_TURN_SPAN", p.wall_turn_max - p.wall_turn_min + 1, "uint16_t"),
                CDefine("KF_WALL_COOLDOWN", p.wall_cooldown, comment="straight periods before the wall counts again"),
                CDefine("KF_UTURN", p.uturn_steps, comment="pivot periods of the U-turn on losing a level"),
                CDefine("KF_SETTLE_PATIENCE", p.settle_patience, comment="non-improving periods before stopping"),
                CDefine("KF_SETTLE_HOLD", p.settle_hold, comment="missed periods before a stopped robot leaves"),
                CDefine("KF_NBR_GRADIENT", int(p.nbr_gradient), comment="level 1: climb the neighbour proximity"),
                CDefine("KF_TURN_RANDOM", int(p.turn_sign == 0), comment="1: draw the turn direction"),
                CDefine("KF_TURN_LEFT", int(p.turn_sign > 0), comment="the fixed direction when not drawn"),
                CDefine("KF_TURN_ALTERNATE", int(p.turn_sign == 2), comment="1: turns at the target alternate"),
                CDefine("KF_PUSH_MARGIN", int(p.push_margin > 0), comment="1: worse only once the distance grew"),
                CDefine("KF_MARGIN_Q", qp.margin_q, comment=f"... by more than this ({p.push_margin:g} at e_in)"),
                CDefine("KF_HOLD_WITHIN", int(p.hold_within), comment="1: a settled robot pushed out drives on"),
                CDefine("KF_BIG", BIG, "int32_t", "run until something happens (periods)"),
                CDefine("KF_SEED_MUL", SEED_MUL, "uint32_t", "xorshift32 seed = kilo_uid * MUL + ADD (never 0)"),
                CDefine("KF_SEED_ADD", SEED_ADD, "uint32_t"),
            ),
            tables=(CTable("KF_RUN", "uint16_t", qp.run_table,
                           "RUN[b]: exploration run length (periods) for draw byte b, u = (b + 0.5) / 256",
                           per_line=12),))


SEARCHER = SearcherKind()
