"""What the hand-written (rule) kinds share: their random stream, their calibration and their error report.

A rule kind (``searcher``, ``aggregator``, ``stop_in_light``, ``run_and_tumble``) has no weights: its firmware runs a float rule's steps on the int8
observation every kind builds, with a few bytes of state. Its randomness is a per-robot xorshift32 word
(Marsaglia's 13/17/5 triple) seeded in ``setup()`` from ``kilo_uid`` (``uid * 0x9E3779B1 + 0x7F4A7C15``, never
0); kilolib's ``rand_soft`` is not used: its generator is kilolib's and no emulator could follow it bit for bit,
while this one the emulator models exactly, on the robot, under Kilombo and in the host and AVR builds alike.
Robots with equal uids draw alike.

The calibration is the recorded input tuples (nothing to calibrate); the error report runs the float rule
drawing from the firmware's streams on the recorded float observations next to the integer rule on the
quantised ones: what quantising the observation changes. :class:`RuleKind` answers the kind's questions
that do not depend on the rule (its artifact holds no arrays, only its parameters; its size is fixed).
"""
from __future__ import annotations

import dataclasses
from abc import abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping

import numpy as np

from sim.config import ACTION_DIM, WorldConfig
from sim.motion import action_to_u8

from ..errors import InputError, PolicyError
from ..validate import show
from ..xorshift import SEED_ADD, SEED_MUL, rng_seed, top_byte, xorshift32  # noqa: F401  (the kinds import them here)
from .base import ActorKind, FloatPolicy, QuantizedActor, Resize

PROB_BITS = 16  #: a probability P is drawn as r < ceil(P * 2**16) with r a uniform 16-bit number
PROB_ONE = 1 << PROB_BITS


def prob_threshold(p: np.ndarray) -> np.ndarray:
    """int64 thresholds ceil(P * 2**16) in 0..2**16: ``r / 2**16 < P`` exactly when ``r < threshold``."""
    return np.ceil(np.asarray(p, np.float64) * PROB_ONE).astype(np.int64)


def draw_bytes(word: np.ndarray) -> np.ndarray:
    """(R, 4) int64 bytes of xorshift32 words, least significant first."""
    w = np.asarray(word, np.uint32).astype(np.int64)
    return np.stack([(w >> (8 * i)) & 0xFF for i in range(4)], -1)


class OwnSeeds:
    """Mixin of a float rule ``(cfg, params)`` whose ``reset`` without a generator takes the next child of its own
    seed sequence (the closed loop and FloatPolicy.step reset it so)."""

    def __init__(self, cfg: WorldConfig, params: Any, seed: int = 0) -> None:
        super().__init__(cfg, params)  # type: ignore[call-arg]
        self._seeds = np.random.SeedSequence(seed)

    def reset(self, n_envs: int, n_robots: int, rng: np.random.Generator | None = None) -> None:
        super().reset(n_envs, n_robots,  # type: ignore[misc]
                      rng if rng is not None else np.random.default_rng(self._seeds.spawn(1)[0]))


class UidStreams:
    """Mixin of a float rule ``(cfg, params)`` drawing from the firmware's xorshift32 streams, one per robot seeded
    by its uid: after ``reset`` ``self.word`` (n_envs, n_robots) is what setup() leaves; its ``draws`` steps it."""

    def __init__(self, cfg: WorldConfig, params: Any, uids: np.ndarray) -> None:
        super().__init__(cfg, params)  # type: ignore[call-arg]
        self.uids = np.asarray(uids, np.uint16)

    def reset(self, n_envs: int, n_robots: int, rng: np.random.Generator | None = None) -> None:
        assert n_envs * n_robots == self.uids.size, "one uid per robot"
        super().reset(n_envs, n_robots, np.random.default_rng(0))  # type: ignore[misc]  # never drawn from
        self.word = rng_seed(self.uids).reshape(n_envs, n_robots)


@dataclass(frozen=True, eq=False)
class RuleCalibration:
    """The recorded input tuples (S, T, D) of the float rule's rollouts."""

    seqs: np.ndarray
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def n(self) -> int:
        return int(self.seqs.shape[0] * self.seqs.shape[1])


@dataclass(frozen=True)
class RuleError:
    """Integer rule on quantised observations vs the float rule on the recorded float ones, both drawing from
    the firmware's streams (uid i + 1 for row i): what quantising the observation changes."""

    kind: str
    du_max: float
    du_mean: float
    same_command: float  #: fraction of (robot, step, motor) with equal uint8 commands
    same_step: float  #: fraction of (robot, step) with both commands equal
    n_samples: int
    e_in: int

    def table(self) -> str:
        return (f"{self.kind} quantisation error over {self.n_samples} recorded steps (e_in = {self.e_in}; same random "
                f"draws, float vs quantised observations): same uint8 command {100 * self.same_command:.2f}%, both "
                f"motors {100 * self.same_step:.2f}%, max |du| = {self.du_max:.5f}, mean |du| = {self.du_mean:.5f}")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def rule_error(ref: Any, qp: Any, calib: RuleCalibration) -> RuleError:
    """:class:`RuleError` over the calibration sequences; ``ref`` is the float rule drawing from the firmware's
    streams of uids 1..S, reset for one env of S robots."""
    seqs = np.asarray(calib.seqs, np.float64)
    S, T, _ = seqs.shape
    state = qp.setup_state(np.arange(1, S + 1))
    du, same, both = [], 0, 0
    for t in range(T):
        u = ref.act(seqs[None, :, t, ACTION_DIM:])[0]
        q, state = qp.step_int(qp.quantize_tuple(seqs[:, t]), state)
        uf = action_to_u8(u)
        du.append(np.abs(q / 255.0 - u))
        same += int((q == uf).sum())
        both += int((q == uf).all(-1).sum())
    d = np.stack(du)
    return RuleError(kind=qp.kind, du_max=float(d.max()), du_mean=float(d.mean()), same_command=same / (2 * S * T),
                     same_step=both / (S * T), n_samples=S * T, e_in=qp.e_in)


def params_from_meta(cls: type, meta_params: Any, later: Mapping[str, Any] | None = None) -> Any:
    """``cls`` (a rule's parameter dataclass, which checks its fields) from an artifact's ``params``: every field;
    a field of ``later`` (added after the first files were written) reads as its value there. Raises PolicyError."""
    names = [f.name for f in dataclasses.fields(cls)]
    if not isinstance(meta_params, dict):
        raise PolicyError(f"policy: 'params' must be an object, got {show(meta_params)}")
    meta_params = {**(later or {}), **meta_params}
    missing, extra = [n for n in names if n not in meta_params], sorted(set(meta_params) - set(names))
    if missing or extra:
        raise PolicyError(f"policy: 'params' lacks {missing} / has unknown {extra}" if missing and extra else
                          f"policy: 'params' lacks {', '.join(missing)}" if missing else
                          f"policy: 'params' has unknown field(s) {', '.join(extra)}")
    try:
        return cls(**meta_params)
    except InputError as e:
        raise PolicyError(f"policy: {e}") from None


class RuleActor:
    """Mixin of a rule kind's quantised actor (before QuantizedActor): no dense layers, one tuple in, the state of
    n robots what :meth:`setup_state` gives kilo_uids 0..n-1."""

    @property
    def layers(self) -> list:
        """No dense layers."""
        return []

    @property
    def layer_sizes(self) -> list[int]:
        return [self.world.tuple_dim, ACTION_DIM]  # type: ignore[attr-defined]

    def initial_state(self, n: int) -> Any:
        """The state of n robots with kilo_uid 0..n-1 (the emulator calls ``setup_state`` with the real ones)."""
        return self.setup_state(np.arange(n))  # type: ignore[attr-defined]


class RuleKind(ActorKind):
    """A hand-written rule's kind: no arrays, nothing to calibrate, one size (:attr:`arch`), the error report of
    :func:`rule_error`. A subclass gives its policy, quantiser, firmware-draw reference, budget and render spec."""

    c_sources: ClassVar[tuple[str, ...]] = ()
    arch: ClassVar[type]  #: its (fieldless) size dataclass

    @abstractmethod
    def policy_of(self, meta_params: Any, world: WorldConfig, provenance: dict[str, Any]) -> FloatPolicy:
        """The float policy of an artifact's ``params`` (one-line PolicyError)."""

    @abstractmethod
    def quantize_rule(self, policy: Any, e_in: int | None) -> QuantizedActor:
        """The integer rule (e_in: the default input exponent unless given)."""

    @abstractmethod
    def draw_reference(self, policy: Any, uids: np.ndarray) -> Any:
        """The float rule drawing from the firmware's streams of these uids (a sim.rollout.SwarmPolicy)."""

    def from_arrays(self, arrays: dict[str, np.ndarray], meta: dict[str, Any], world: WorldConfig,
                    provenance: dict[str, Any]) -> FloatPolicy:
        if arrays:
            raise PolicyError(f"policy: a {self.name} has no arrays, found {', '.join(sorted(arrays))}")
        if "params" not in meta:
            raise PolicyError("policy: 'meta' lacks 'params'")
        return self.policy_of(meta["params"], world, provenance)

    def calibration(self, policy: FloatPolicy, seqs: np.ndarray, info: dict[str, Any]) -> RuleCalibration:
        return RuleCalibration(np.asarray(seqs, np.float32), dict(info))

    def quantize(self, policy: FloatPolicy, calib: RuleCalibration, *, percentile: float = 100.0,
                 headroom: float = 1.0, e_in: int | None = None) -> QuantizedActor:
        """No ranges to cover: e_in is the default input exponent unless given."""
        return self.quantize_rule(policy, e_in)

    def error_report(self, policy: FloatPolicy, qp: QuantizedActor, calib: RuleCalibration) -> RuleError:
        S = int(np.asarray(calib.seqs).shape[0])
        ref = self.draw_reference(policy, np.arange(1, S + 1))
        ref.reset(1, S)
        return rule_error(ref, qp, calib)

    def arch_of(self, policy: FloatPolicy) -> Any:
        return self.arch()

    def arch_of_quantized(self, qp: QuantizedActor) -> Any:
        return self.arch()

    def resizes(self, world: WorldConfig, arch: Any) -> list[Resize]:
        return []

    def budget_arch(self, values: Mapping[str, Any]) -> Any:
        return self.arch() if any(values.get(o.dest) for o in self.budget_options) else None
