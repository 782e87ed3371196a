"""Actor kind ``"aggregator"``: the hand-written probabilistic aggregation rule of :mod:`sim.tasks.aggregation` as firmware.

The float actor is :class:`sim.tasks.aggregation.ProbabilisticAggregator` itself; its artifact holds no arrays,
only the :class:`~sim.tasks.aggregation.AggregatorParams` in the meta (``params``: every field), and records the
task it is for (aggregation). The shipped one is ``export/data/aggregator_policy.npz`` (the tuned defaults in
aggregation's kilobot world), written by ``python -m tools.ship_rules`` (tests/test_aggregator_firmware.py fails
on a stale file).

The integer rule (:meth:`QuantizedAggregator.step_int`, rendered by ``firmware_templates/actors/aggregator.c.j2``)
runs the float rule's steps on the int8 observation (wall flag and RBF histogram at ``e_in``) with 7 bytes of
state. Everything it compares is exact:

* **neighbours**: the float rule's n is the RBF sum over one mid-range neighbour's, rounded half up, at most
  :data:`~sim.tasks.aggregation.NBR_MAX`: ``n = #{j : sum >= x_j}`` with ``x_j = (j - 0.5) · per_neighbour``.
  The firmware sums its int8 bins (``S``, at most ``n_rbf · 127``) and counts ``S >= NBR_T[j]`` with
  ``NBR_T[j] = ceil(x_j · 2**e_in)`` (uint16): for the dequantised sum ``S / 2**e_in`` both counts agree,
  since scaling by a power of two is exact.
* **probabilities**: each period the robot's xorshift32 word (:mod:`kiloforge.actors.rules`, seeded from
  ``kilo_uid``) is stepped twice. The first word's low half ``r`` (16 bits) decides stopping and leaving, its
  high half ``t`` starting a random turn; the second word's byte 0 is the turn's pivots ``1 + (b · turn_max >> 8)``
  and its byte 1 the direction (left when < 128). The float ``u < P`` with ``u = r / 2**16`` is exactly
  ``r < ceil(P · 2**16)``, so the thresholds ``STOP_T[n]``, ``LEAVE_T[n]`` (uint32, 0..2**16, one per n) and
  ``TUMBLE_T`` come from the float rule's own :func:`~sim.tasks.aggregation.stop_prob`,
  :func:`~sim.tasks.aggregation.leave_prob` and :func:`~sim.tasks.aggregation.tumble_prob`: each probability is
  realised within 2**-16 of the float's.
* **wall**: ``2 obs_wall > ONE`` (the float ``> 0.5`` on 0 / 1).

:class:`FirmwareDrawAggregator` is the float rule taking its draws from these words: fed the dequantised
observations it gives exactly the integer rule's commands (the test of the integer reference). The only
differences between the float rule and the firmware are the observation's quantisation (an int8 bin saturates
at 127, about 8 neighbours at one distance) and the random streams (NumPy vs xorshift32).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping

import numpy as np

from sim.config import ACTION_DIM, WorldConfig
from sim.tasks import get_task
from sim.tasks.aggregation import (NBR_MAX, AggregatorParams, ProbabilisticAggregator, leave_prob, nbr_thresholds,
                                   stop_prob, tumble_prob)
from sim.tasks.base import TaskRef

from .. import numfmt
from ..artifact import plain_provenance
from ..errors import QuantizeError
from .base import (BudgetItem, BudgetOption, BudgetSpec, CDefine, CTable, FloatPolicy, QuantizedActor, RenderSpec,
                   check_world_and_task, invalid, sensing_tables)
from .rules import (PROB_BITS, PROB_ONE, SEED_ADD, SEED_MUL, OwnSeeds, RuleActor, RuleKind, UidStreams, draw_bytes,
                    params_from_meta, prob_threshold, rng_seed, xorshift32)

STATE_BYTES = 4 + 3  #: rng (uint32) + resting, turn_left, turn_dir (uint8)
FEATURES = ("wall", "rbf")  #: the observation features the rule reads
TASK = "aggregation"  #: the task the rule is for


def firmware_draws(p: AggregatorParams, w1: np.ndarray, w2: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The period's draws from its two xorshift32 words: the 16-bit stop / leave and turn numbers, the turn's
    pivots and direction (True: left)."""
    a = np.asarray(w1, np.uint32).astype(np.int64)
    b = draw_bytes(w2)
    return a & 0xFFFF, a >> 16, 1 + ((b[..., 0] * p.turn_max_steps) >> 8), b[..., 1] < 128


# --------------------------------------------------------------------------------------------
# The float rule and its random draws
# --------------------------------------------------------------------------------------------
class SeededAggregator(OwnSeeds, ProbabilisticAggregator):
    """The float rule; ``reset`` without a generator takes the next child of its own seed sequence."""


class FirmwareDrawAggregator(UidStreams, ProbabilisticAggregator):
    """The float rule drawing from the firmware's xorshift32 streams (one per robot, seeded by uid)."""

    def draws(self, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        w1 = xorshift32(self.word)
        self.word = xorshift32(w1)
        r, t, steps, left = firmware_draws(self.p, w1, self.word)
        return r / PROB_ONE, t / PROB_ONE, steps, left


# --------------------------------------------------------------------------------------------
# The float policy (the artifact)
# --------------------------------------------------------------------------------------------
def check_world(world: WorldConfig) -> None:
    """The rule reads the wall flag and the RBF histogram; one-line PolicyError when the world lacks one."""
    missing = [f for f in FEATURES if not world.has_feature(f)]
    if missing:
        invalid(f"the aggregator reads {', '.join(FEATURES)}; world '{world.name}' observes {world.obs_features}")


@dataclass(frozen=True, eq=False)
class AggregatorPolicy(FloatPolicy):
    """The probabilistic aggregation rule with its parameters in a world; no arrays."""

    kind: ClassVar[str] = "aggregator"
    params: AggregatorParams
    world: WorldConfig
    provenance: dict[str, Any] = field(default_factory=dict)
    task: TaskRef | None = None

    def __post_init__(self) -> None:
        check_world_and_task(self.world, self.task)
        if not isinstance(self.params, AggregatorParams):
            invalid(f"params must be AggregatorParams, got {type(self.params).__name__}")
        check_world(self.world)
        object.__setattr__(self, "provenance", plain_provenance(self.provenance))

    @property
    def layer_sizes(self) -> list[int]:
        """[tuple width, 2]: no layers, the rule reads one tuple."""
        return [self.world.tuple_dim, ACTION_DIM]

    def describe(self) -> str:
        p = self.params
        return (f"hand-written aggregator (stop {p.stop_base:g} + {p.stop_per_nbr:g} n, leave {p.leave_base:g} / "
                f"(1 + {p.leave_decay:g} n^2), runs of {p.run_steps} periods)")

    def arrays(self) -> dict[str, np.ndarray]:
        return {}

    def kind_meta(self) -> dict[str, Any]:
        return {"params": dataclasses.asdict(self.params)}

    def initial_state(self, n: int) -> SeededAggregator:
        """A float rule of n robots (its own generator, seed 0)."""
        s = SeededAggregator(self.world, self.params)
        s.reset(1, n)
        return s

    def step(self, x: np.ndarray, state: SeededAggregator) -> tuple[np.ndarray, SeededAggregator]:
        """Tuples (n, D) -> the rule's commands on their observation part (the state is updated in place)."""
        obs = np.asarray(x, np.float64)[:, ACTION_DIM:]
        return state.act(obs[None])[0], state


def aggregator_policy(world: WorldConfig, params: AggregatorParams | None = None,
                      provenance: Mapping[str, Any] | None = None) -> AggregatorPolicy:
    """The aggregator artifact of task aggregation in ``world`` made the task's (default: the tuned parameters)."""
    task = get_task(TASK)
    notes = "sim.tasks.aggregation.ProbabilisticAggregator, AggregatorParams tuned on validation episodes"
    return AggregatorPolicy(params if params is not None else AggregatorParams(), task.world(world),
                            dict(provenance or {"notes": notes}), task.ref)


# --------------------------------------------------------------------------------------------
# The integer rule
# --------------------------------------------------------------------------------------------
@dataclass
class AggregatorState:
    """Per robot (R,): the firmware's aggregator fields."""

    rng: np.ndarray  #: uint32 xorshift32 word
    resting: np.ndarray  #: bool
    turn_left: np.ndarray  #: pivot periods still to do (0..255)
    turn_dir: np.ndarray  #: bool, True: left


@dataclass(frozen=True, eq=False, kw_only=True)
class QuantizedAggregator(RuleActor, QuantizedActor):
    """The integer rule (module doc): the float parameters and their firmware thresholds."""

    kind: ClassVar[str] = "aggregator"
    params: AggregatorParams
    nbr_t: np.ndarray  #: (NBR_MAX,) uint16: n >= j + 1 neighbours when the int8 RBF sum >= nbr_t[j]
    stop_t: np.ndarray  #: (NBR_MAX + 1,) uint32: a walking robot with n neighbours stops when r < stop_t[n]
    leave_t: np.ndarray  #: (NBR_MAX + 1,) uint32: a resting one leaves when r < leave_t[n]
    tumble_t: int  #: an idle walking robot starts a random turn when t < tumble_t

    def __post_init__(self) -> None:
        super().__post_init__()
        assert self.nbr_t.shape == (NBR_MAX,) and self.nbr_t.dtype == np.uint16, "nbr_t shape/dtype"
        assert (np.diff(self.nbr_t.astype(np.int64)) >= 0).all(), "nbr_t must not decrease"
        for t in (self.stop_t, self.leave_t):
            assert t.shape == (NBR_MAX + 1,) and t.dtype == np.uint32 and t.max() <= PROB_ONE, "threshold table"
        assert 0 <= self.tumble_t <= PROB_ONE, "tumble_t out of range"

    def setup_state(self, uids: np.ndarray) -> AggregatorState:
        """What setup() leaves: every field 0, the generator seeded from kilo_uid."""
        z = np.zeros(np.asarray(uids).shape[0], np.int64)
        return AggregatorState(rng=rng_seed(uids), resting=z.astype(bool), turn_left=z, turn_dir=z.astype(bool))

    def neighbours(self, obs: np.ndarray) -> np.ndarray:
        """(R,) int64 neighbours heard from int8 observations (R, obs_dim)."""
        total = np.asarray(obs, np.int64)[:, self.world.obs_slice("rbf")].sum(-1)
        return (total[:, None] >= self.nbr_t.astype(np.int64)).sum(-1)

    def step_int(self, x: np.ndarray, state: AggregatorState) -> tuple[np.ndarray, AggregatorState]:
        """int8 tuples (R, D) and the state -> (uint8 commands (R, 2), the new state); the float rule's steps."""
        p = self.params
        o = np.asarray(x, np.int64)[:, ACTION_DIM:]
        n = self.neighbours(o)
        w1 = xorshift32(state.rng)
        w2 = xorshift32(w1)
        r, t, steps, left = firmware_draws(p, w1, w2)
        stop = ~state.resting & (r < self.stop_t.astype(np.int64)[n])
        leave = state.resting & (r < self.leave_t.astype(np.int64)[n])
        resting = (state.resting | stop) & ~leave
        walking = ~resting
        idle = walking & (state.turn_left == 0)
        wall = idle & (2 * o[:, self.world.obs_index("wall")] > self.one_q)
        tumble = idle & ~wall & (t < self.tumble_t)
        turn_left = np.where(wall, p.wall_turn_steps, np.where(tumble, steps, state.turn_left))
        turn_dir = np.where(wall | tumble, left, state.turn_dir)
        turning = walking & (turn_left > 0)
        q = np.zeros((o.shape[0], ACTION_DIM), np.uint8)
        q[:, 0] = np.where(turning, np.where(turn_dir, 0, 255), np.where(walking, 255, 0))
        q[:, 1] = np.where(turning, np.where(turn_dir, 255, 0), np.where(walking, 255, 0))
        new = AggregatorState(rng=w2, resting=resting, turn_left=np.where(turning, turn_left - 1, turn_left),
                              turn_dir=turn_dir)
        return q, new

    def summary(self) -> dict[str, Any]:
        return {"kind": self.kind, "format": self.format_name, "rounding": self.rounding, "e_in": int(self.e_in),
                "params": dataclasses.asdict(self.params), "nbr_max": NBR_MAX,
                "nbr_t": self.nbr_t.tolist(), "stop_t": self.stop_t.tolist(), "leave_t": self.leave_t.tolist(),
                "tumble_t": int(self.tumble_t), "prob_bits": PROB_BITS,
                "rng": "xorshift32 (13, 17, 5) stepped twice per period, seed kilo_uid * 0x9E3779B1 + 0x7F4A7C15",
                "policy_hash": self.policy_hash, "world": self.world.name}

    def describe(self) -> str:
        return (f"hand-written aggregator: n from the RBF sum (one neighbour ~ {int(self.nbr_t[1] - self.nbr_t[0])} "
                f"units), stop/leave thresholds out of 2^{PROB_BITS}, e_in {self.e_in}")


def quantize_aggregator(policy: AggregatorPolicy, e_in: int | None = None) -> QuantizedAggregator:
    """The integer rule of ``policy`` (its thresholds from the float rule's own probability functions)."""
    p, w = policy.params, policy.world
    e = numfmt.DEFAULT_INPUT_EXP if e_in is None else int(e_in)
    if not 0 <= e <= numfmt.DEFAULT_INPUT_EXP:
        raise QuantizeError(f"e_in must be in 0..{numfmt.DEFAULT_INPUT_EXP}, got {e}")
    x = nbr_thresholds(w) * (1 << e)
    if not (x > 0).all() or x[-1] > 0xFFFF:
        raise QuantizeError(f"world '{w.name}': one neighbour's RBF sum {x[0] * 2:g} (at e_in) does not give "
                            f"uint16 neighbour thresholds")
    n = np.arange(NBR_MAX + 1)
    return QuantizedAggregator(params=p, nbr_t=np.ceil(x).astype(np.uint16),
                               stop_t=prob_threshold(stop_prob(p, n)).astype(np.uint32),
                               leave_t=prob_threshold(leave_prob(p, n)).astype(np.uint32),
                               tumble_t=int(prob_threshold(tumble_prob(p))), e_in=e, world=w,
                               policy_hash=policy.hash, **sensing_tables(w, e))


# --------------------------------------------------------------------------------------------
# The kind
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class AggregatorArch:
    """The aggregator's size does not vary: a fixed state, three threshold tables, the rule."""


#: code beside the base estimate: the rule and xorshift32 minus the dense kernels the base counts and this program
#: leaves out; measured: avr-gcc 9,868 B flash for the kilobot aggregator vs 10,733 B analytic at -2,600
CODE_B = -3_450


class AggregatorKind(RuleKind):
    """The probabilistic aggregation rule of sim.tasks.aggregation (the baseline to flash next to a learned policy)."""

    name: ClassVar[str] = "aggregator"
    template: ClassVar[str] = "actors/aggregator.c.j2"
    arch = AggregatorArch
    budget_usage: ClassVar[str] = "--aggregator probabilistic"
    budget_options: ClassVar[tuple[BudgetOption, ...]] = (
        BudgetOption("--aggregator", "the hand-written aggregation rule (its size does not depend on its parameters)",
                     metavar="RULE", positive=False, choices=("probabilistic",)),
    )

    def policy_of(self, meta_params: Any, world: WorldConfig, provenance: dict[str, Any]) -> AggregatorPolicy:
        return AggregatorPolicy(params_from_meta(AggregatorParams, meta_params), world, provenance)

    def swarm_policy(self, policy: AggregatorPolicy, world: WorldConfig | None = None) -> SeededAggregator:
        """The float rule of sim.tasks.aggregation (its own generator unless reset gets one)."""
        return SeededAggregator(world or policy.world, policy.params)

    def quantize_rule(self, policy: AggregatorPolicy, e_in: int | None) -> QuantizedAggregator:
        return quantize_aggregator(policy, e_in)

    def draw_reference(self, policy: AggregatorPolicy, uids: np.ndarray) -> FirmwareDrawAggregator:
        return FirmwareDrawAggregator(policy.world, policy.params, uids)

    def budget_spec(self, world: WorldConfig, arch: AggregatorArch, e_in: int) -> BudgetSpec:
        return BudgetSpec(
            header="hand-written aggregator (no dense layers)", layer_sizes=(world.tuple_dim, ACTION_DIM), dense=(),
            flash=(BudgetItem("flash", "neighbour thresholds", 2 * NBR_MAX, f"{NBR_MAX} x uint16"),
                   BudgetItem("flash", "stop / leave thresholds", 2 * 4 * (NBR_MAX + 1), f"2 x {NBR_MAX + 1} x uint32")),
            memory=(BudgetItem("sram", "aggregator state", STATE_BYTES, "rng (4 B) + resting, turn, direction"),),
            scratch=(BudgetItem("sram", "tuple buffer", world.tuple_dim, f"{world.tuple_dim} int8"),),
            code_b=CODE_B, code_note="(the aggregation rule, without the dense kernels; estimate)")

    def render_spec(self, qp: QuantizedAggregator) -> RenderSpec:
        p = qp.params
        return RenderSpec(
            memory=(),
            scratch=(
                CDefine("KF_NBR_MAX", NBR_MAX, comment="neighbours are counted up to this many"),
                CDefine("KF_TUMBLE_T", qp.tumble_t, "uint32_t",
                        f"start a random turn when the 16-bit draw < this (1 / {p.run_steps} of 2^16)"),
                CDefine("KF_TURN_MAX", p.turn_max_steps, comment="a random turn pivots 1..this many periods"),
                CDefine("KF_WALL_TURN", p.wall_turn_steps, comment="pivot periods away from a lit wall"),
                CDefine("KF_SEED_MUL", SEED_MUL, "uint32_t", "xorshift32 seed = kilo_uid * MUL + ADD (never 0)"),
                CDefine("KF_SEED_ADD", SEED_ADD, "uint32_t"),
            ),
            tables=(CTable("KF_NBR_T", "uint16_t", qp.nbr_t,
                           "n >= j + 1 neighbours when the RBF sum >= NBR_T[j] ((j + 0.5) neighbours at e_in)",
                           per_line=12),
                    CTable("KF_STOP_T", "uint32_t", qp.stop_t,
                           f"STOP_T[n] = ceil(2^16 min(1, {p.stop_base:g} + {p.stop_per_nbr:g} n))", per_line=8),
                    CTable("KF_LEAVE_T", "uint32_t", qp.leave_t,
                           f"LEAVE_T[n] = ceil(2^16 {p.leave_base:g} / (1 + {p.leave_decay:g} n^2))", per_line=8)))


AGGREGATOR = AggregatorKind()
