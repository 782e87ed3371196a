"""Firmware in the loop: the simulator driven by the int8 firmware emulator vs by the float actor.

Rung 4 of the verification ladder (docs/verification.md). Two runs over exactly the same episodes:

* **int8**: every searcher's command comes from :class:`export.verify.emulator.FirmwareEmulator` (the
  bit-exact model of the generated C) fed with the radio events and light readings the simulator
  produced; the command goes back into the simulator with :meth:`sim.env.SwarmEnv.step_u8`
  (``kilobot`` preset: the real motor schedule tick by tick; ``thesis`` preset: ``u = q / 255``).
  One emulator holds all ``R = B * M`` robots of a batch of B envs; the task's emitter, if it has one, is
  simulated (it is not a robot of the env), so the emulator runs only the searchers.
* **float**: the float policy through its kind's swarm policy (an MLP: :class:`sim.rollout.HistoryActor`)
  and ``SwarmEnv.step``.

Both runs derive the env seed of batch k exactly as :func:`sim.rollout.rollout` does, so episode i
starts from the same positions with the same radio and light random streams in both runs, and the
float run equals ``rollout(SwarmEnv(cfg, B, M), swarm_policy(policy), episodes, seed)``.
Differences between the two runs are the quantisation (weights, activations, observations from
uint8 distances and tables) and nothing else.

Timing (the control-step contract, docs/design.md; see :mod:`export.verify.emulator`): ``SwarmEnv.reset`` listens
one still period; its events go to the emulator as period 0; the emulator's control step k (tick
k·P) decides the commands of simulator step k; the events of that step are period k.

The ``thesis`` radio has no timing: every message of a period arrives at tick 0. Delivered that way,
the firmware's rx queue (``firmware.RXQ_CAPACITY`` messages per tick) would drop what a real robot
hears spread over the period, so for radios without a tick model the messages a receiver gets are
spread over the period's ticks in arrival order (``tick = rank * P // count``), which keeps the
order the receive rules use. Tick-level radios (``kilobot``) are delivered as simulated.
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from kiloforge.actors.base import FloatPolicy, QuantizedActor
from kiloforge.policies import swarm_policy
from sim.config import WorldConfig
from sim.env import SwarmEnv
from sim.events import HeardEvents
from sim.metrics import Summary, summarise
from sim.rollout import EpisodeLoop, TaskEpisodes
from sim.tasks import Task, get_task

from .emulator import FirmwareEmulator, events_from_sim

GOAL_RATIO = 0.97  #: the int8 primary metric (final success) must reach this fraction of the float actor's
ROBOT_BUDGET = 2048  #: default cap on B * M robots at once (throughput peaks near 1-2k robots, bench_closed_loop)
BOOTSTRAP = 2000  #: resamples of the paired bootstrap CI of the primary metric's ratio


# --------------------------------------------------------------------------------------------
# Seeds and batches (shared with sim.rollout.rollout)
# --------------------------------------------------------------------------------------------
def batch_env_seeds(seed: int, n_batches: int) -> list[int]:
    """Env seed of each batch, derived as :func:`sim.rollout.rollout` derives it.

    >>> batch_env_seeds(0, 2) == batch_env_seeds(0, 3)[:2]
    True
    """
    out = []
    for ss in np.random.SeedSequence(seed).spawn(n_batches):
        env_ss, _policy_ss = ss.spawn(2)
        out.append(int(env_ss.generate_state(1, np.uint32)[0]))
    return out


def default_n_envs(episodes: int, n_robots: int, robot_budget: int = ROBOT_BUDGET) -> int:
    """Envs per batch: at most ``robot_budget // n_robots``, balanced so the last batch is not short.

    >>> default_n_envs(200, 16), default_n_envs(200, 32), default_n_envs(200, 64), default_n_envs(3, 4)
    (100, 50, 29, 3)
    """
    assert episodes >= 1 and n_robots >= 1, "episodes and n_robots must be >= 1"
    cap = max(1, min(episodes, robot_budget // n_robots))
    n_batches = math.ceil(episodes / cap)
    return math.ceil(episodes / n_batches)


def spread_ticks(events: HeardEvents, n_robots: int, period_ticks: int) -> HeardEvents:
    """Spread each receiver's messages of one period over its ticks, in arrival order.

    ``tick = rank * P // count`` for the receiver's ``rank``-th of ``count`` messages: arrival order
    is kept, and no tick gets more than ``ceil(count / P)`` messages.

    >>> z = np.zeros(3, np.int32)
    >>> ev = HeardEvents(z, z.copy(), np.array([-1, 0, 2], np.int32), np.zeros(3, np.int16),
    ...                  np.ones(3), np.array([1, 0, 0], np.uint8), np.zeros(3, np.uint8))
    >>> spread_ticks(ev, 3, 31).tick.tolist()
    [0, 10, 20]
    """
    n = len(events)
    if n == 0:
        return events
    o = events.arrival_order(n_robots)
    group = events.env[o].astype(np.int64) * n_robots + events.rx[o]  # (N,) non-decreasing
    start = np.r_[0, np.flatnonzero(np.diff(group)) + 1]
    count = np.diff(np.r_[start, n])
    rank = np.arange(n) - np.repeat(start, count)
    tick = (rank * period_ticks) // np.repeat(count, count)  # (N,) in 0..P-1
    return HeardEvents(events.env[o], events.rx[o], events.sender[o], tick.astype(np.int16),
                       events.dist_mm[o], events.role[o], events.flag[o])


# --------------------------------------------------------------------------------------------
# Controllers: who decides the commands of a batch
# --------------------------------------------------------------------------------------------
class _FloatController:
    """The float actor (its kind's swarm policy); commands go through SwarmEnv.step."""

    label = "float"
    command_dtype = np.float32  #: what a record keeps of the commands

    def __init__(self, policy: FloatPolicy, cfg: WorldConfig) -> None:
        self.actor = swarm_policy(policy, cfg)

    def send(self, env):
        return env.step

    def start(self, env, obs: np.ndarray, info) -> None:
        self.actor.reset(env.n_envs, env.n_robots)

    def act(self, env, obs: np.ndarray, info) -> np.ndarray:
        return self.actor.act(obs)  # (B, M, 2) float64 in [0, 1]

    def heard(self, info, period: int) -> None:
        pass


class _FirmwareController:
    """The int8 firmware emulator, R = B * M searchers; commands go through SwarmEnv.step_u8."""

    label = "int8"
    command_dtype = np.uint8

    def __init__(self, qp: QuantizedActor, cfg: WorldConfig, spread: bool | None = None) -> None:
        self.qp = qp
        self.cfg = cfg
        self.emu: FirmwareEmulator | None = None
        # thesis radio: every message at tick 0, spread them (module doc)
        self.spread = cfg.msg_period_ticks == 0 if spread is None else bool(spread)

    def start(self, env, obs: np.ndarray, info) -> None:
        B, M = env.n_envs, env.n_robots
        uids = np.tile(np.arange(1, M + 1, dtype=np.int64), B)  # (B * M,) searcher i has uid i + 1
        if self.emu is None or self.emu.R != B * M:
            self.emu = FirmwareEmulator(self.qp, uids)
        self.emu.reset()  # setup(): the first control step starts a new history
        self.heard(info, 0)  # the listening period of SwarmEnv.reset

    def send(self, env):
        return env.step_u8

    def act(self, env, obs: np.ndarray, info) -> np.ndarray:
        B, M = env.n_envs, env.n_robots
        q, _ = self.emu.control_step(np.asarray(info["light"]).reshape(B * M))  # (R, 2) uint8
        return q.reshape(B, M, 2)

    def heard(self, info, period: int) -> None:
        ev = info["events"]
        M = self.emu.R // info["light"].shape[0]
        if self.spread:
            ev = spread_ticks(ev, M, self.cfg.period_ticks)
        self.emu.deliver(events_from_sim(ev, period, self.cfg, M))


# --------------------------------------------------------------------------------------------
# Runs
# --------------------------------------------------------------------------------------------
@dataclass
class LoopResult(TaskEpisodes):
    """Per-episode records of one closed-loop run (E episodes, T steps, M robots)."""

    label: str  #: "float" or "int8"
    cfg: WorldConfig  #: the world (episode_steps as run)
    n_robots: int
    seed: int
    n_envs: int  #: envs per batch (the seeds depend on it; both runs of a comparison share it)
    rewards: np.ndarray  #: (E, T) team reward per step
    success: np.ndarray  #: (E, T) the task's success after each step
    wall_s: float  #: seconds the run took
    positions: np.ndarray | None = None  #: (E, T + 1, M, 2) float64 mm when recorded
    headings: np.ndarray | None = None  #: (E, T + 1, M) float64 rad when recorded
    commands: np.ndarray | None = None  #: (E, T, M, 2) the commands sent (float32 u or uint8 q)
    task: Any = None  #: the task (sim.tasks.Task) the episodes were played for; None: localisation

    @property
    def episodes_per_s(self) -> float:
        return self.episodes / max(self.wall_s, 1e-9)


def _run(controller, cfg: WorldConfig, n_robots: int, episodes: int, seed: int, n_envs: int | None,
         record: bool, bar, task: Task | None) -> LoopResult:
    assert episodes >= 1, f"episodes must be >= 1, got {episodes}"
    task = get_task(task)
    M = int(n_robots)
    assert not 1 <= cfg.emitter_uid <= M, (
        f"emitter_uid {cfg.emitter_uid} is also searcher {cfg.emitter_uid - 1}'s uid; use emitter_uid 0 or > {M}")
    B = int(n_envs) if n_envs is not None else default_n_envs(episodes, M)
    T = cfg.episode_steps
    seeds = batch_env_seeds(seed, math.ceil(episodes / B))
    E = len(seeds) * B
    pos = head = cmds = None
    if record:
        pos = np.zeros((E, T + 1, M, 2))
        head = np.zeros((E, T + 1, M))
        cmds = np.zeros((E, T, M, 2), controller.command_dtype)
    env = SwarmEnv(cfg, B, M, seed=seeds[0], task=task)
    loop = EpisodeLoop(env, len(seeds), send=controller.send(env))

    def begin(k: int, obs, info) -> None:
        controller.start(env, obs, info)
        if record:
            pos[loop.rows, 0], head[loop.rows, 0] = env.pos, env.heading

    def act(t: int, obs, info) -> np.ndarray:
        return controller.act(env, obs, info)

    def observe(t: int, c, obs, r, info) -> None:
        controller.heard(info, t + 1)
        if record:
            rows = loop.rows
            pos[rows, t + 1], head[rows, t + 1] = env.pos, env.heading
            cmds[rows, t] = c
        if bar is not None:
            bar.update(B)

    t0 = time.perf_counter()
    loop.run(act, seeds, begin, observe)
    wall = time.perf_counter() - t0
    keep = slice(0, episodes)
    return LoopResult(controller.label, cfg, M, int(seed), B, loop.rewards[keep], loop.success[keep], wall,
                      None if pos is None else pos[keep], None if head is None else head[keep],
                      None if cmds is None else cmds[keep], task)


def _world(world: WorldConfig, steps: int | None) -> WorldConfig:
    if steps is None:
        return world
    assert int(steps) >= 1, f"steps must be >= 1, got {steps}"
    return dataclasses.replace(world, episode_steps=int(steps))


def run_float(policy: FloatPolicy, n_robots: int, episodes: int, seed: int = 0, *, steps: int | None = None,
              n_envs: int | None = None, record: bool = False, bar=None, task: Task | None = None) -> LoopResult:
    """The float actor in its own world: ``episodes`` episodes of ``steps`` (default: the world's) of ``task``
    (default localisation)."""
    cfg = _world(policy.world, steps)
    return _run(_FloatController(policy, cfg), cfg, n_robots, episodes, seed, n_envs, record, bar, task)


def run_firmware(qp: QuantizedActor, n_robots: int, episodes: int, seed: int = 0, *,
                 steps: int | None = None, n_envs: int | None = None, record: bool = False,
                 bar=None, spread: bool | None = None, task: Task | None = None) -> LoopResult:
    """The int8 firmware (emulator) in the quantised policy's world, same episodes as :func:`run_float`.

    ``spread``: spread each period's messages over its ticks (default: only for radios without a
    tick model, see the module doc).
    """
    cfg = _world(qp.world, steps)
    return _run(_FirmwareController(qp, cfg, spread), cfg, n_robots, episodes, seed, n_envs, record, bar, task)


# --------------------------------------------------------------------------------------------
# Paired comparison
# --------------------------------------------------------------------------------------------
def loop_metrics(task: Task) -> tuple[tuple[str, str], ...]:
    """(key, name) of what a comparison reports: the return, then the task's evaluation metrics (primary first)."""
    return (("return", "return"),) + tuple((k, task.metric(k).long) for k in task.eval_keys)


def ratio_ci(num: np.ndarray, den: np.ndarray, seed: int = 0, n: int = BOOTSTRAP) -> tuple[float, float]:
    """95 % paired-bootstrap interval of mean(num) / mean(den) (episodes resampled together).

    >>> lo, hi = ratio_ci(np.full(10, 0.5), np.full(10, 1.0)); (lo, hi)
    (0.5, 0.5)
    """
    num, den = np.asarray(num, np.float64), np.asarray(den, np.float64)
    assert num.shape == den.shape and num.ndim == 1, "paired 1-D samples"
    rng = np.random.default_rng(np.random.SeedSequence(seed))
    idx = rng.integers(0, num.size, size=(n, num.size))  # (n, E) resampled episodes
    d = den[idx].mean(1)
    r = np.where(d > 0, num[idx].mean(1) / np.where(d > 0, d, 1.0), np.nan)
    if np.all(np.isnan(r)):
        return float("nan"), float("nan")
    lo, hi = np.nanpercentile(r, [2.5, 97.5])
    return float(lo), float(hi)


@dataclass
class Comparison:
    """Float actor vs int8 firmware on the same episodes of one robot count."""

    n_robots: int
    float_run: LoopResult
    int8_run: LoopResult
    goal: float = GOAL_RATIO
    stats: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        f, q = self.float_run, self.int8_run
        assert f.rewards.shape == q.rewards.shape, "the two runs must cover the same episodes"
        assert f.n_envs == q.n_envs and f.seed == q.seed, "the two runs must use the same seeds"
        self.task = get_task(f.task)
        self.primary = self.task.primary_metric
        mf, mq = f.metrics(), q.metrics()
        for key, _ in loop_metrics(self.task):
            a, b = mf.per_episode(key), mq.per_episode(key)
            self.stats[key] = {"float": summarise(a), "int8": summarise(b), "diff": summarise(b - a)}
        pf, pq = mf.per_episode(self.primary), mq.per_episode(self.primary)
        self.ratio = pq.mean() / pf.mean() if pf.mean() > 0 else float("nan")
        self.ratio_ci = ratio_ci(pq, pf, seed=f.seed)

    @property
    def episodes(self) -> int:
        return self.float_run.episodes

    @property
    def passed(self) -> bool:
        """int8 mean of the task's primary metric >= goal * the float's (point
        estimates; 0 >= 0 passes)."""
        f = self.stats[self.primary]
        return bool(f["int8"].mean >= self.goal * f["float"].mean - 1e-12)

    def curves(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Per run: the mean success per step (T,) and its 95 % CI half-width (T,)."""
        out = {}
        for run in (self.float_run, self.int8_run):
            c = run.success  # (E, T)
            half = np.array([summarise(c[:, t]).ci95 for t in range(c.shape[1])])  # Student t per step
            out[run.label] = (c.mean(axis=0), half)
        return out

    def table(self) -> str:
        """Float vs int8 side by side: mean ± 95 % CI, the paired difference, ratio and verdict."""
        f, q = self.float_run, self.int8_run
        lines = [f"{self.n_robots} robots, {self.episodes} episodes x {f.steps} steps "
                 f"(world '{f.cfg.name}', seed {f.seed}, {f.n_envs} envs per batch)",
                 ]
        rows = loop_metrics(self.task)
        w = max(15, *(len(label) for _, label in rows))
        lines.append(f"  {'metric':<{w}} {'float actor':>17} {'int8 firmware':>17} {'int8 - float (paired)':>22}")
        for key, label in rows:
            s = self.stats[key]
            lines.append(f"  {label:<{w}} {_pm(s['float']):>17} {_pm(s['int8']):>17} {_pm(s['diff'], signed=True):>22}")
        lo, hi = self.ratio_ci
        verdict = "PASS" if self.passed else "FAIL"
        name = self.task.metric(self.primary).long
        ratio = (f"{self.ratio:.4f} (95% CI {lo:.4f}..{hi:.4f})" if np.isfinite(self.ratio)
                 else f"n/a (the float actor's {name} is 0)")
        lines.append(f"  {name} int8/float = {ratio}; goal >= {self.goal:.2f}: {verdict}")
        lines.append(f"  speed: float {f.episodes_per_s:.1f} episodes/s, int8 {q.episodes_per_s:.1f} episodes/s")
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        f, q = self.float_run, self.int8_run
        curves = self.curves()
        return {
            "n_robots": self.n_robots, "episodes": self.episodes, "steps": f.steps, "seed": f.seed,
            "n_envs": f.n_envs, "world": f.cfg.name,
            "metrics": {k: {side: s.to_dict() for side, s in v.items()} for k, v in self.stats.items()},
            f"{self.primary}_ratio": _num(self.ratio), f"{self.primary}_ratio_ci95": [_num(x) for x in self.ratio_ci],
            "goal_ratio": self.goal, "passed": self.passed,
            "episodes_per_s": {"float": f.episodes_per_s, "int8": q.episodes_per_s},
            "wall_s": {"float": f.wall_s, "int8": q.wall_s},
            "success_curve": {k: {"mean": m.tolist(), "ci95": h.tolist()} for k, (m, h) in curves.items()},
            "per_episode": {side: {k: run.metrics().per_episode(k).tolist() for k, _ in loop_metrics(self.task)}
                            for side, run in (("float", f), ("int8", q))},
        }


def _num(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def _pm(s: Summary, signed: bool = False) -> str:
    sign = "+" if signed else ""
    return f"{s.mean:{sign}.3f} ± {s.ci95:.3f}"


def compare(policy: FloatPolicy, qp: QuantizedActor, n_robots: int, episodes: int, seed: int = 0, *,
            steps: int | None = None, n_envs: int | None = None, goal: float = GOAL_RATIO, bar=None,
            task: Task | None = None) -> Comparison:
    """Float actor vs int8 firmware, same ``episodes`` (same env seeds) of ``task`` (default localisation), one
    robot count."""
    if policy.world.to_dict() != qp.world.to_dict():
        raise ValueError("the quantised policy was made for another world than the float policy")
    B = n_envs if n_envs is not None else default_n_envs(episodes, n_robots)
    f = run_float(policy, n_robots, episodes, seed, steps=steps, n_envs=B, bar=bar, task=task)
    q = run_firmware(qp, n_robots, episodes, seed, steps=steps, n_envs=B, bar=bar, task=task)
    return Comparison(int(n_robots), f, q, goal=goal)


def compare_many(policy: FloatPolicy, qp: QuantizedActor, robots: Sequence[int], episodes: int, seed: int = 0,
                 *, steps: int | None = None, goal: float = GOAL_RATIO, progress: bool = False,
                 task: Task | None = None) -> list[Comparison]:
    """:func:`compare` for each robot count, with one tqdm bar (episode-steps) over all of them."""
    T = steps if steps is not None else policy.world.episode_steps
    bar = None
    if progress:
        from kiloforge.progress import progress_bar

        total = sum(2 * default_n_envs(episodes, m) * math.ceil(episodes / default_n_envs(episodes, m)) * T
                    for m in robots)
        bar = progress_bar(total=total, unit="ep-step", desc="closed loop (float + int8)", leave=False)
    try:
        return [compare(policy, qp, m, episodes, seed, steps=steps, goal=goal, bar=bar, task=task) for m in robots]
    finally:
        if bar is not None:
            bar.close()
