"""Baseline policies: uniform random commands, and a hand-written searcher (the bar to beat).

:class:`HandWrittenSearcher` uses only what one robot has: its own observation vector (wall flag,
target distance or -1, "a neighbour senses the target" flag, RBF histogram of neighbour distances)
and a few bytes of its own state (timers, the previous level and score). Every rule is a comparison
or a counter, so it ports directly to a Kilobot. Vectorised over (B envs, M robots): no Python loop
over robots.

Behaviour, per robot and control period, by *level* of what it senses:

* level 2 — the target is heard: climb the target-distance gradient (run and tumble: keep going
  while the distance shrinks, turn a random amount when it grows); stop for good once the distance is
  at most ``stop_dist`` of the comm radius, or after ``settle_patience`` non-improving periods. A
  stopped robot leaves only after missing the target ``settle_hold`` periods in a row (message loss).
* level 1 — no target, but a neighbour says it senses the target (so the target is within two comm
  radii): run and tumble on a neighbour-proximity score (RBF histogram weighted towards near bins).
* level 0 — nothing: explore with a correlated random walk (straight runs, Lévy-like or
  exponential lengths, random tumbles) and turn away when the wall flag is set.
* whenever the level drops (the robot has just left the target's or the neighbour's range) it makes a
  U-turn, which takes it straight back in.

The *pusher* (:data:`PUSHER`, ``make_policy("pusher", …)``) is the same searcher with three parameters set for
crowds at the target: it stops only within 0.94 of the range, at level 2 it counts a period as worse only once
the distance has grown by ``push_margin`` above its best since the last turn (so a robot blocked by the crowd
keeps pushing straight instead of tumbling along its edge), and a settled robot pushed out beyond its stopping
distance drives on (``hold_within``), counting its best from where it was pushed to. It packs 32 robots closer
than the searcher (docs/results/localisation.md).

Commands are only ``(speed, speed)`` (straight), ``(1, 0)`` / ``(0, 1)`` (one turn period: ≈45°; in
the thesis kinematics with 5 mm forward, in the kilobot preset a pivot) and ``(0, 0)`` (stop).
Parameters: :class:`SearcherParams`; tuned values per preset in :data:`TUNED`.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from kiloforge.errors import InputError

from .config import ACTION_DIM, WorldConfig


class RandomPolicy:
    """Independent uniform commands in [0, 1]² for every robot and step."""

    def __init__(self) -> None:
        self.rng: np.random.Generator | None = None

    def reset(self, n_envs: int, n_robots: int, rng: np.random.Generator) -> None:
        self.rng = rng

    def act(self, obs: np.ndarray) -> np.ndarray:
        assert self.rng is not None, "RandomPolicy.act before reset"
        return self.rng.random(obs.shape[:2] + (ACTION_DIM,))


COUNTER_MAX = 255  #: the firmware's searcher counters are uint8
RUN_MAX = 0xFFFF  #: run lengths are uint16 in the firmware's run table
#: the closed range of each numeric SearcherParams field (speed excludes 0); what a robot can hold
PARAM_RANGES: dict[str, tuple[float, float]] = {
    "speed": (0.0, 1.0), "run_min_steps": (1.0, float(RUN_MAX)), "run_alpha": (0.0, 1000.0),
    "run_max_steps": (1, RUN_MAX), "tumble_max_steps": (1, COUNTER_MAX), "wall_turn_min": (1, COUNTER_MAX),
    "wall_turn_max": (1, COUNTER_MAX), "wall_cooldown": (0, COUNTER_MAX), "uturn_steps": (0, COUNTER_MAX),
    "stop_dist": (0.0, 1.0), "settle_patience": (1, COUNTER_MAX - 1), "settle_hold": (1, COUNTER_MAX - 1),
    "turn_sign": (-1, 2), "push_margin": (0.0, 1.0)}
_KIND_NAMES = {"bool": "true or false", "int": "an integer", "float": "a number"}


def check_fields(params: object, ranges: dict[str, tuple[float, float]], what: str,
                 open_zero: tuple[str, ...] = ()) -> None:
    """Every field of the dataclass ``params`` of its annotated type (bool, int, float) and in its range of
    ``ranges`` (closed; a field of ``open_zero`` excludes 0); raises InputError ``<what> parameter NAME ...``."""
    for f in dataclasses.fields(params):  # type: ignore[arg-type]
        v = getattr(params, f.name)
        kind = f.type if isinstance(f.type, str) else f.type.__name__
        ok = isinstance(v, bool) if kind == "bool" else \
            isinstance(v, int) and not isinstance(v, bool) if kind == "int" else \
            isinstance(v, (int, float)) and not isinstance(v, bool)
        if not ok:
            raise InputError(f"{what} parameter {f.name} must be {_KIND_NAMES[kind]}, got {v!r}")
        if f.name in ranges:
            lo, hi = ranges[f.name]
            if not (lo <= v <= hi) or (f.name in open_zero and v == 0):
                shown = f"({lo:g}, {hi:g}]" if f.name in open_zero else f"[{lo}, {hi}]"
                raise InputError(f"{what} parameter {f.name} must be in {shown}, got {v!r}")


@dataclass(frozen=True)
class SearcherParams:
    """Constants of :class:`HandWrittenSearcher` (each one a byte or two in firmware)."""

    speed: float = 1.0  #: command of both motors on a straight run
    run_min_steps: float = 25.0  #: exploration: shortest straight run (periods)
    run_alpha: float = 1.5  #: Pareto tail exponent of run lengths (Lévy-like); 0 = exponential, mean run_min
    run_max_steps: int = 300  #: runs are cut at this length
    tumble_max_steps: int = 3  #: a tumble pivots 1..this many periods (≈45° each at full turn)
    wall_turn_min: int = 3  #: a wall turn pivots between these many periods ...
    wall_turn_max: int = 3  #: ... (3 ≈ 135°; tuned: 180° sends robots back on their own track)
    wall_cooldown: int = 2  #: straight periods after a wall turn before the wall flag counts again
    uturn_steps: int = 4  #: pivot periods of the U-turn made on losing the target / neighbour (≈180°)
    stop_dist: float = 1.0  #: stop once the target is heard at <= this fraction of the comm radius
    settle_patience: int = 6  #: ... or after this many non-improving periods inside the target range
    settle_hold: int = 3  #: a stopped robot moves on after missing the target this many periods in a row
    nbr_gradient: bool = True  #: level 1: run and tumble on neighbour proximity (else keep going)
    #: turn direction: 0 = random left/right per turn; +1 always left, -1 always right; 2 = left, but turns at
    #: level 2 alternate right, left, … (the deterministic choices a learner can imitate: learn.demos)
    turn_sign: int = 0
    #: level 2 only: a period counts as worse only once the distance has grown by more than this fraction of the
    #: comm radius above its best since the last turn (0: any non-improving period is worse). Robots blocked by a
    #: crowd at the target then keep pushing straight instead of tumbling along its edge
    push_margin: float = 0.0
    #: a settled robot that hears the target beyond ``stop_dist`` (pushed out of the band) drives straight on
    #: instead of holding there; its best distance (``push_margin``) starts again from where it was pushed to
    hold_within: bool = False

    def __post_init__(self) -> None:
        """Every field of its type and in its range (:data:`PARAM_RANGES`; the firmware holds the counters in a
        byte, run lengths in 16 bits, so the simulator and the export accept the same parameters);
        raises :class:`kiloforge.errors.InputError` naming the field and its range."""
        check_fields(self, PARAM_RANGES, "searcher", open_zero=("speed",))
        if self.turn_sign not in (-1, 0, 1, 2):
            raise InputError(f"searcher parameter turn_sign must be -1, 0, 1 or 2, got {self.turn_sign}")
        if self.run_min_steps > self.run_max_steps:
            raise InputError(f"searcher parameters need run_min_steps <= run_max_steps, got "
                             f"{self.run_min_steps} > {self.run_max_steps}")
        if self.wall_turn_min > self.wall_turn_max:
            raise InputError(f"searcher parameters need wall_turn_min <= wall_turn_max, got "
                             f"{self.wall_turn_min} > {self.wall_turn_max}")
        if self.wall_turn_max + self.wall_cooldown > COUNTER_MAX:
            raise InputError(f"searcher parameters need wall_turn_max + wall_cooldown <= {COUNTER_MAX} (one uint8 "
                             f"counter), got {self.wall_turn_max + self.wall_cooldown}")


#: tuned parameters per world preset (the dataclass defaults are the thesis values). Kilobot discs
#: crowd the target, so they walk further in before stopping; its 40 mm wall zone needs a longer
#: cooldown. Sweeps and results: see the sim-tools report / README.
TUNED: dict[str, SearcherParams] = {
    "thesis": SearcherParams(),
    "kilobot": SearcherParams(run_min_steps=30, tumble_max_steps=2, wall_cooldown=3, stop_dist=0.6),
}

#: the names :func:`make_policy` knows (``--policy`` of ``python -m sim`` takes them too)
BASELINE_NAMES = ("random", "baseline", "pusher")

#: what the pusher changes in a world's tuned searcher (module doc; 0.05 of the kilobot range is 4.25 mm: 5 mm on
#: whole-mm readings)
PUSHER = {"stop_dist": 0.94, "push_margin": 0.05, "hold_within": True}


def run_lengths(p: SearcherParams, u: np.ndarray) -> np.ndarray:
    """Exploration run lengths (periods, int32) for uniform draws ``u`` in [0, 1): Pareto(α) above
    ``run_min_steps`` (exponential with mean ``run_min_steps`` when α = 0), rounded up, cut at ``run_max_steps``."""
    u = np.asarray(u, np.float64)
    if p.run_alpha > 0:
        with np.errstate(over="ignore"):  # a small α overflows to inf for u near 1: cut at run_max below
            r = p.run_min_steps * (1.0 - u) ** (-1.0 / p.run_alpha)  # Pareto(α), ≥ run_min
    else:
        r = -p.run_min_steps * np.log1p(-u)  # exponential, mean run_min
    return np.minimum(np.ceil(r), p.run_max_steps).astype(np.int32)


class HandWrittenSearcher:
    """A run-and-tumble searcher that a Kilobot could run; see the module docstring."""

    def __init__(self, cfg: WorldConfig, params: SearcherParams | None = None) -> None:
        self.cfg = cfg
        self.p = params if params is not None else TUNED.get(cfg.name, SearcherParams())
        n = cfg.n_rbf
        # neighbour proximity weights: nearest bin 1, farthest 1/n (a constant table in firmware)
        self.prox_w = (n - np.arange(n)) / n  # (n_rbf,)
        self.rng: np.random.Generator | None = None

    # --- state --------------------------------------------------------------------------------
    def reset(self, n_envs: int, n_robots: int, rng: np.random.Generator) -> None:
        shape = (n_envs, n_robots)
        self.rng = rng
        self.turn_left = np.zeros(shape, np.int32)  # pivot periods still to do
        self.turn_dir = np.full(shape, -1, np.int8)  # +1 left (counter-clockwise), -1 right (as the firmware's 0)
        self.run_left = np.zeros(shape, np.int32)  # straight periods still to do (exploration)
        self.wall_cool = np.zeros(shape, np.int32)  # periods during which the wall flag is ignored
        self.prev_level = np.zeros(shape, np.int8)  # 0 nothing, 1 neighbour senses target, 2 target heard
        self.prev_score = np.zeros(shape)  # gradient signal of the previous period
        self.best = np.zeros(shape)  # best target score since the last turn (push_margin)
        self.fails = np.zeros(shape, np.int32)  # non-improving periods in the target range
        self.settled = np.zeros(shape, bool)  # stopped at the target
        self.miss = np.zeros(shape, np.int32)  # consecutive periods a settled robot missed the target

    def draws(self, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """This period's random draws for every robot: (turn direction ±1, tumble periods, wall-turn
        periods, run length). Drawn every period whether used or not (fixed consumption ⇒
        reproducible streams); a subclass may take them from elsewhere (the firmware's generator)."""
        p, rng = self.p, self.rng
        dirs = np.where(rng.random(shape) < 0.5, 1, -1).astype(np.int8)
        tumble = rng.integers(1, p.tumble_max_steps + 1, shape)
        wall_turn = rng.integers(p.wall_turn_min, p.wall_turn_max + 1, shape)
        return dirs, tumble, wall_turn, run_lengths(p, rng.random(shape))

    # --- decision -----------------------------------------------------------------------------
    def act(self, obs: np.ndarray) -> np.ndarray:
        assert self.rng is not None, "HandWrittenSearcher.act before reset"
        p = self.p
        B, M, _ = obs.shape
        shape = (B, M)
        w = self.cfg
        wall = obs[..., w.obs_index("wall")] > 0.5
        tdist = obs[..., w.obs_index("target")]  # distance / comm radius, -1 when not heard
        heard = tdist >= 0
        nbr = obs[..., w.obs_index("nbr_sensing")] > 0.5
        prox = obs[..., w.obs_slice("rbf")] @ self.prox_w  # (B, M) neighbour proximity
        level = np.where(heard, 2, np.where(nbr, 1, 0)).astype(np.int8)
        score = np.where(heard, -tdist, prox)

        dirs, tumble, wall_turn, runs = self.draws(shape)
        if p.turn_sign == 2:
            dirs = np.where(level == 2, -self.turn_dir, 1).astype(np.int8)
        elif p.turn_sign:
            dirs = np.full(shape, p.turn_sign, np.int8)  # the draw still happened: same stream whatever the sign

        # settled robots: hold position through short target dropouts
        self.miss = np.where(self.settled & ~heard, self.miss + 1, 0)
        pushed_out = self.settled & heard & (tdist > p.stop_dist) if p.hold_within else np.zeros(shape, bool)
        leave = self.settled & (self.miss >= p.settle_hold)
        holding = self.settled & ~leave
        level = np.where(holding, 2, level).astype(np.int8)  # a holding robot still counts as at the target
        holding &= ~pushed_out
        self.settled = holding

        turning = self.turn_left > 0
        same = (level == self.prev_level) & (level >= 1) & ~holding  # a gradient to compare
        improved = same & (score > self.prev_score)
        worse = same & ~improved & ~turning
        if p.push_margin > 0:
            push = same & (level == 2)
            worse = np.where(push, ~turning & (score < self.best - p.push_margin), worse)
        entered = (level > self.prev_level) | pushed_out
        lost = (level < self.prev_level) | leave

        def start_turn(mask: np.ndarray, steps: np.ndarray, run: np.ndarray | int) -> None:
            self.turn_left = np.where(mask, steps, self.turn_left)
            self.turn_dir = np.where(mask, dirs, self.turn_dir)
            self.run_left = np.where(mask, run, self.run_left)

        big = np.int32(1 << 20)
        # level 0: exploration tumbles when a run ends
        start_turn((level == 0) & ~turning & (self.run_left <= 0), tumble, runs)
        # levels 1–2: gradient run and tumble
        grad = (level == 2) | ((level == 1) & p.nbr_gradient)
        start_turn(grad & worse, tumble, big)
        self.run_left = np.where(grad & improved & ~turning, big, self.run_left)
        self.fails = np.where((level == 2) & worse, self.fails + 1, np.where(level == 2, self.fails, 0))
        # walls: turn away (any moving robot), then ignore the flag for a few straight periods
        hit_wall = wall & (self.wall_cool <= 0) & ~turning
        start_turn(hit_wall, wall_turn, np.maximum(self.run_left, p.wall_cooldown))
        self.wall_cool = np.where(hit_wall, wall_turn + p.wall_cooldown, self.wall_cool - 1)
        # entering a higher level: head on straight (we are pointing inwards)
        start_turn(entered, 0, big)
        # dropping a level: U-turn straight back in
        start_turn(lost & ~entered, p.uturn_steps, runs)
        self.fails = np.where(lost | entered, 0, self.fails)
        # settle at the target
        self.settled |= (level == 2) & heard & ((tdist <= p.stop_dist) | (self.fails >= p.settle_patience))

        # motor commands
        turn_now = (self.turn_left > 0) & ~self.settled
        straight = ~turn_now & ~self.settled
        a = np.zeros(shape + (ACTION_DIM,))
        left = turn_now & (self.turn_dir > 0)
        right = turn_now & (self.turn_dir < 0)
        a[..., 0] = np.where(left, 1.0, np.where(straight, p.speed, 0.0))  # u_left
        a[..., 1] = np.where(right, 1.0, np.where(straight, p.speed, 0.0))  # u_right
        self.turn_left = np.where(turn_now, self.turn_left - 1, self.turn_left)
        self.run_left = np.where(straight, self.run_left - 1, self.run_left)
        self.prev_level = level
        self.prev_score = score
        self.best = np.where(same & ~turning & ~entered, np.maximum(self.best, score), score)
        return a


def make_policy(name: str, cfg: WorldConfig, **params) -> "RandomPolicy | HandWrittenSearcher":
    """``"random"``, ``"baseline"`` (the hand-written searcher, tuned for ``cfg.name``) or ``"pusher"`` (the same
    with :data:`PUSHER`); ``params`` replace searcher parameters."""
    if name == "random":
        return RandomPolicy()
    if name in ("baseline", "pusher"):
        base = TUNED.get(cfg.name, SearcherParams())
        changes = {**(PUSHER if name == "pusher" else {}), **params}
        return HandWrittenSearcher(cfg, dataclasses.replace(base, **changes) if changes else base)
    raise ValueError(f"unknown baseline policy '{name}'; choose one of {', '.join(BASELINE_NAMES)}")
