"""The one experiment loop for every algorithm and actor: collect, replay, update, evaluate, checkpoint.

:func:`train` runs a :class:`learn.config.TrainConfig` (MAGDDPG, MLP actor) or a
:class:`learn.config.RecurrentConfig` (MAGRDPG, recurrent actor); the algorithm
(:data:`ALGORITHMS`) supplies everything that differs between them — how a robot's actor input or
state is built while acting, how the replay is sampled (transitions or burn-in windows), behaviour
cloning, and the policy artifact — so the loop has no branch on the actor kind.

Read top to bottom: seeding (one ``SeedSequence``, one stream per consumer), one env group per swarm
size (:mod:`learn.groups`), the guided preparation with a demonstrator (demonstrations, behaviour
cloning, critic pre-training; :mod:`learn.demos`), then one loop over batches of ``n_envs``
synchronised episodes per size. Each step every robot acts with Ornstein-Uhlenbeck noise, the joint
transition goes to its size's replay, and after the warm-up the owed updates (``updates_per_step``
per transition) run in blocks every ``update_every`` steps and at the episode end. At episode ends the
trainer evaluates every ``eval_every`` transitions (each size on fixed episodes), logs (CSV, curve,
TensorBoard), exports the policies and checkpoints (incrementally, :mod:`learn.checkpoint`).

Resume is exact: a run resumed from a checkpoint continues as if it had never stopped (networks,
optimisers, replay, every RNG stream, counters). SIGKILL loses only what came after the last
checkpoint. SIGINT / SIGTERM (:mod:`learn.interrupt`) finish the episode batch under way (with its
updates, evaluation and logging, as an uninterrupted run would), checkpoint at that boundary and exit
130 / 143, so a resumed run is exactly the uninterrupted one; a second signal stops at once and keeps the
last checkpoint (as SIGKILL would).
The run directory's files are listed in :mod:`learn.rundir`.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from kiloforge.io import write_atomic

from .checkpoint import Checkpointer
from .config import ConfigError, ExperimentConfig, RecurrentConfig, TrainConfig
from .demos import bc_pretrain, collect_demos, demonstrator
from .evaluate import Evaluator, LearnerPolicy, evaluate_sizes, metrics_row, row_summary, success_panel
from .groups import EnvGroup, size_shares
from .interrupt import Interrupted, StopRequest
from .magddpg import MAGDDPG
from .magrdpg import MAGRDPG
from .replay import EpisodeReplay
from .rundir import (METRIC_COLUMNS, RESUME_MAY_CHANGE, Counters, RunResult, check_resumable,  # noqa: F401
                     finite_or_none, git_hash, prepare_run_dir, rows_to_csv, run_name, write_summary)
from .runfiles import read_metrics
from .speed import UpdateThreads, resolve_device, set_threads, threads_differ, tune_allocator

CHECKPOINT_VERSION = 2
PLOT_EVERY_S = 60.0  #: redraw learning_curve.png at most this often (and at the end): plotting is slow
ALGORITHMS = {"magddpg": MAGDDPG, "magrdpg": MAGRDPG}  #: algorithm class of each config's ``algorithm``

__all__ = ["train", "RunResult", "Counters", "TrainConfig", "RecurrentConfig", "read_metrics", "rows_to_csv",
           "run_name", "METRIC_COLUMNS", "RESUME_MAY_CHANGE"]


def train(cfg: ExperimentConfig, run_dir: str | os.PathLike, resume: bool = False, progress: bool = True,
          log: Callable[[str], None] = print) -> RunResult:
    """Train with ``cfg`` (any algorithm), writing to ``run_dir``; ``resume`` continues from its checkpoint
    (or restarts a run directory that has none). Returns the counters and why the run stopped."""
    cfg.validate()
    device = resolve_device(cfg.device)
    run_dir = Path(run_dir)
    resume = prepare_run_dir(run_dir, resume, log)
    ckpt = Checkpointer(run_dir)
    world = cfg.world_config()
    set_threads(cfg.threads)
    tune_allocator()
    T = world.episode_steps

    # --- seeding: one SeedSequence, one stream per consumer; no global NumPy RNG ----------------
    ss_init, ss_env, ss_noise, ss_replay, ss_eval, ss_aug, ss_demo = np.random.SeedSequence(cfg.seed).spawn(7)
    torch.manual_seed(int(ss_init.generate_state(1, np.uint64)[0]))
    env_rng = np.random.default_rng(ss_env)  # env construction and episode reset seeds
    noise_rng = np.random.default_rng(ss_noise)
    sample_rng = np.random.default_rng(ss_replay)
    aug_rng = np.random.default_rng(ss_aug)  # phantom neighbours (off unless phantom_neighbours > 0)
    demo_rng = np.random.default_rng(ss_demo)  # demonstrations and behaviour cloning
    eval_seed = int(ss_eval.generate_state(1, np.uint32)[0])

    # --- algorithm, env groups, evaluators --------------------------------------------------------
    algo = ALGORITHMS[cfg.algorithm].from_config(cfg, world, device)
    groups = [EnvGroup(cfg, world, M, algo, env_rng, noise_rng, aug_rng) for M in cfg.n_robots]
    eval_randomise = cfg.randomise if cfg.randomise_eval else "none"
    evaluators = [Evaluator(world, M, cfg.eval_episodes, eval_seed, eval_randomise, cfg.task_spec()) for M in cfg.n_robots]
    shares = size_shares(cfg.batch_samples, cfg.n_robots, cfg.size_mix)
    demo_shares = size_shares(cfg.demo_samples, cfg.n_robots, cfg.size_mix)
    c = Counters()
    result = RunResult(run_dir, c, "done")
    prep = Preparation(cfg, world, algo, groups, evaluators, run_dir, progress, log)

    def replays() -> list:
        return [g.replay for g in groups] + [g.demos for g in groups if g.demos is not None]

    def snapshot() -> dict:
        return {"version": CHECKPOINT_VERSION, "algorithm": cfg.algorithm, "config": cfg.to_dict(),
                "agent": algo.state_dict(),
                "rng": {"env": env_rng.bit_generator.state, "noise": noise_rng.bit_generator.state,
                        "replay": sample_rng.bit_generator.state, "augment": aug_rng.bit_generator.state,
                        "demo": demo_rng.bit_generator.state, "torch": torch.get_rng_state()},
                "counters": vars(c)}

    def save() -> None:
        t0 = time.perf_counter()
        c.wall_s = wall_at_start + (time.perf_counter() - session_start)
        ckpt.save(snapshot(), replays())
        c.checkpoint_s += time.perf_counter() - t0

    def export(name: str, metrics: dict) -> None:
        from kiloforge.policies import save_policy

        save_policy(dataclasses.replace(algo.artifact(world, provenance(cfg, algo, c, metrics)), task=cfg.task_spec().ref),
                    run_dir / name)

    stop = StopRequest()
    tb = None
    bar = None
    session_start = time.perf_counter()
    wall_at_start = 0.0
    guided = cfg.demo_policy != "none"
    prepared = False  # the guided phases are done (an interrupt from here on checkpoints)
    with stop:
        try:
            if resume:
                for g in groups:  # filled from the checkpoint
                    g.demos = prep.empty_demos(g, algo.replay_t_prev) if guided else None
                state = ckpt.load(replays())
                ckpt.clean()  # orphans of a run killed while checkpointing
                if state.get("version") != CHECKPOINT_VERSION:
                    raise ConfigError(f"checkpoint version {state.get('version')} is not supported "
                                      f"(expected {CHECKPOINT_VERSION})")
                check_resumable(state["config"], cfg)
                algo.load_state_dict(state["agent"])
                for rng, name in ((env_rng, "env"), (noise_rng, "noise"), (sample_rng, "replay"),
                                  (aug_rng, "augment"), (demo_rng, "demo")):
                    rng.bit_generator.state = state["rng"][name]
                torch.set_rng_state(state["rng"]["torch"])
                c = result.counters = Counters(**state["counters"])
                log(f"resumed {run_dir} at {c.env_steps} transitions, {c.updates} updates")
            else:
                ckpt.clean()
                write_atomic(run_dir / "config.json", cfg.to_json() + "\n")
                write_atomic(run_dir / "world.json", json.dumps(world.to_dict(), indent=2, sort_keys=True) + "\n")
                for g in groups:
                    g.demos = prep.collect(g, demo_rng, stop, algo.replay_t_prev) if guided else None
                if guided and cfg.bc_updates:
                    c.best_return = prep.clone(demo_rng, shares, stop, export)
                if guided and cfg.critic_pretrain:
                    prep.critic(sample_rng, shares, demo_shares, stop)
            prepared = True
            wall_at_start = c.wall_s
            session_start = time.perf_counter()
            if cfg.tensorboard:
                from .tblog import TensorBoardLog

                tb = TensorBoardLog(run_dir, purge_step=c.env_steps if resume else None)
            if progress:
                from kiloforge.progress import progress_bar

                total = cfg.total_episodes * T
                bar = progress_bar(total=total, initial=min(c.env_steps, total), unit="step", dynamic_ncols=True,
                                   desc=run_dir.name[:40], smoothing=0.05, max_seconds=60 * cfg.max_minutes)
            result.stopped = run_loop(cfg, algo, groups, evaluators, c, sample_rng, env_rng, shares, demo_shares,
                                      stop, bar, tb, run_dir, export, save, log,
                                      lambda: wall_at_start + (time.perf_counter() - session_start))
        except (Interrupted, KeyboardInterrupt) as e:
            result.stopped = "interrupted"
            result.signal = e.signum if isinstance(e, Interrupted) else stop.requested or 2
            if prepared and isinstance(e, Interrupted):  # run_loop checkpointed at an episode boundary
                export("policy_last.npz", c.rows[-1] if c.rows else {})
                log("interrupted: checkpoint written; --resume continues from it exactly")
            elif prepared and ckpt.exists():  # a second signal: stopped at once, the last checkpoint stays
                log("stopped at once: the last checkpoint stays; --resume continues from it exactly")
            else:
                log("interrupted before training started: no checkpoint; --resume restarts the run")
        finally:
            if bar is not None:
                bar.close()
            if tb is not None:
                tb.close()
    c.wall_s = wall_at_start + (time.perf_counter() - session_start)
    write_summary(run_dir, cfg, c, result.stopped)
    return result


def run_loop(cfg, algo, groups, evaluators, c: Counters, sample_rng, env_rng, shares, demo_shares, stop, bar, tb,
             run_dir: Path, export, save, log, wall) -> str:
    """Batches of synchronised episodes until the budget is spent; returns why it stopped."""
    T = cfg.world_config().episode_steps
    per_step = sum(g.n_envs for g in groups)  # transitions per control step, all sizes
    session_start = time.perf_counter()
    last_plot = -math.inf
    train_returns, losses = c.pending_returns, c.pending_losses  # since the last evaluation (checkpointed)
    noticed = False

    def stop_at_boundary() -> None:
        """At an episode boundary, after a stop request: checkpoint and stop (resume is then exact)."""
        if stop.requested:
            save()
            raise Interrupted(stop.requested)

    def minibatch(rng: np.random.Generator) -> list:
        parts = []
        for g, n, nd in zip(groups, shares, demo_shares):
            parts.append((algo.sample(g.replay, n, rng), False))
            if nd and g.demos is not None:
                parts.append((algo.sample(g.demos, nd, rng), True))
        return parts

    def one_update() -> None:
        actor_turn = c.updates >= cfg.actor_delay and (c.updates - cfg.actor_delay) % cfg.policy_every == 0
        st = algo.update_parts(minibatch(sample_rng), cfg.bc_weight, train_actor=actor_turn)
        losses.append([st.critic_loss, st.q_mean, st.bc_pass])
        c.updates += 1

    threads = UpdateThreads(cfg.threads, algo.device,
                            differs=lambda n: threads_differ(algo, minibatch(np.random.default_rng(0)), cfg.bc_weight, n))

    while c.episodes < cfg.total_episodes:
        stop_at_boundary()
        t0 = time.perf_counter()
        upd_time = 0.0
        for g in groups:
            g.begin(env_rng)
        learning = c.episodes >= cfg.warmup_episodes
        for t in range(T):
            for g in groups:
                truncated = g.step()
            c.env_steps += per_step
            if learning:
                c.update_debt += per_step * cfg.updates_per_step
                if (t + 1) % cfg.update_every == 0 or t == T - 1:
                    u0 = time.perf_counter()
                    n = int(c.update_debt)
                    with threads.block(n) as k:
                        for _ in range(n):
                            one_update()
                    c.update_debt -= n
                    if n:
                        c.update_threads[str(k)] = c.update_threads.get(str(k), 0) + n
                    c.update_threads_note = threads.why_one
                    upd_time += time.perf_counter() - u0
            if bar is not None:
                bar.update(per_step)
            if stop.requested and not noticed:
                noticed = True
                msg = (f"stopping: finishing this episode batch ({T - 1 - t} steps left) and checkpointing, so "
                       f"--resume is exact; a second signal stops at once (the last checkpoint stays)")
                bar.write(msg) if bar is not None else log(msg)
        assert np.all(truncated), "the env did not truncate after episode_steps steps"
        c.episodes += per_step
        for g in groups:
            train_returns.extend(g.ep_return.tolist())
        c.update_s += upd_time
        c.env_s += time.perf_counter() - t0 - upd_time
        c.wall_s = wall()

        # ---- evaluation, logging, checkpoint --------------------------------------------------
        over_time = cfg.max_minutes > 0 and (time.perf_counter() - session_start) >= 60 * cfg.max_minutes
        last = c.episodes >= cfg.total_episodes or over_time
        if c.env_steps >= c.next_eval or last:
            e0 = time.perf_counter()
            plot = last or time.perf_counter() - last_plot >= PLOT_EVERY_S
            evaluate_and_log(cfg, algo, evaluators, c, train_returns, losses, run_dir, export, log, bar, tb, plot,
                             demos=any(g.demos is not None for g in groups))
            last_plot = time.perf_counter() if plot else last_plot
            train_returns.clear()
            losses.clear()
            while c.next_eval <= c.env_steps:
                c.next_eval += cfg.eval_every
            c.eval_s += time.perf_counter() - e0
            if last or (cfg.checkpoint_every and c.evals % cfg.checkpoint_every == 0):
                save()
        if over_time:
            return "time"
    return "done"  # also after a signal during the last episode batch: the run is complete


def evaluate_and_log(cfg, algo, evaluators, c: Counters, train_returns, losses, run_dir: Path, export, log, bar, tb,
                     plot: bool = True, demos: bool = False) -> None:
    """Evaluate every swarm size deterministically, append a metrics row (eval_* = mean over sizes, and
    per size when there are several), export best/last, log, redraw the curve when ``plot``."""
    from .plots import plot_learning_curves

    world = evaluators[0].world
    metrics, per_size = evaluate_sizes(evaluators, lambda: LearnerPolicy(algo, world))
    row = {"env_steps": c.env_steps, "episodes": c.episodes, "updates": c.updates, "wall_s": round(c.wall_s, 2),
           **metrics,
           "train_return": float(np.mean(train_returns)) if train_returns else float("nan"),
           "critic_loss": float(np.mean([x[0] for x in losses])) if losses else float("nan"),
           "q_mean": float(np.mean([x[1] for x in losses])) if losses else float("nan"),
           "env_steps_per_s": c.env_steps / c.env_s if c.env_s > 0 else float("nan"),
           "updates_per_s": c.updates / c.update_s if c.update_s > 0 else float("nan")}
    if demos:
        row["bc_pass"] = mean_finite([x[2] for x in losses])  # NaN while the actor waits
    row.update(per_size)
    c.rows.append(row)
    c.evals += 1
    export("policy_last.npz", row)
    if row["eval_return"] > c.best_return:
        c.best_return = row["eval_return"]
        export("policy_best.npz", row)
    write_atomic(run_dir / "metrics.csv", rows_to_csv(c.rows, cfg.task_spec()))
    if tb is not None:
        tb.row(row)
    if plot:
        plot_learning_curves({run_dir.name: c.rows}, run_dir / "learning_curve.png", title=curve_title(cfg, algo),
                             success=success_panel(cfg.task_spec()))
    msg = f"return {row['eval_return']:.1f}  {row_summary(row, cfg.task_spec())}"
    if bar is not None:
        bar.set_postfix_str(f"{msg}  upd/s {row['updates_per_s']:.0f}", refresh=True)
    else:
        log(f"[{c.env_steps} steps, {c.updates} updates, {c.wall_s:.0f} s] {msg}")


def curve_title(cfg: ExperimentConfig, algo) -> str:
    robots = "/".join(map(str, cfg.n_robots))
    return f"{algo.name}, {robots} robots, {algo.describe()} ({cfg.world} world)"


def mean_finite(xs: list[float]) -> float:
    """Mean of the finite values (NaN when there are none)."""
    v = [x for x in xs if math.isfinite(x)]
    return float(np.mean(v)) if v else float("nan")


def provenance(cfg: ExperimentConfig, algo, c: Counters, metrics: dict) -> dict:
    """What a policy artifact records about the run that made it."""
    robots = cfg.n_robots[0] if len(cfg.n_robots) == 1 else list(cfg.n_robots)
    return {"trainer": f"kiloforge.learn {algo.name}", "config": cfg.to_dict(), "seed": cfg.seed, "git": git_hash(),
            "torch": torch.__version__, "trained_robots": robots, "env_steps": c.env_steps, "updates": c.updates,
            "wall_s": round(c.wall_s, 1), "eval": finite_or_none(dict(metrics))}


class Preparation:
    """The guided phases before reinforcement learning: demonstrations, behaviour cloning, critic pre-training."""

    def __init__(self, cfg, world, algo, groups, evaluators, run_dir: Path, progress: bool, log) -> None:
        self.cfg, self.world, self.algo, self.groups, self.evaluators = cfg, world, algo, groups, evaluators
        self.run_dir, self.progress, self.log = run_dir, progress, log

    def bar(self, total: int, unit: str, desc: str):
        """A transient tqdm bar for one phase (a silent no-op bar without ``progress``)."""
        from kiloforge.progress import progress_bar

        return progress_bar(total=total, unit=unit, desc=desc, dynamic_ncols=True, leave=False,
                            disable=not self.progress)

    def empty_demos(self, g: EnvGroup, t_prev: int) -> EpisodeReplay:
        """A demonstration replay of the shape :meth:`collect` fills (to load from a checkpoint)."""
        T, B = self.world.episode_steps, self.cfg.n_envs
        episodes = -(-self.cfg.demo_episodes // B) * B
        return EpisodeReplay(episodes * T, T, g.n_robots, self.world.tuple_dim, self.world.state_dim(g.n_robots),
                             t_prev, self.algo.device, self.cfg.critic_obs)

    def collect(self, g: EnvGroup, rng: np.random.Generator, stop: StopRequest, t_prev: int):
        """The demonstrator's episodes for one swarm size (regenerated identically on resume: same stream)."""
        cfg = self.cfg
        t0 = time.perf_counter()

        def tick(n: int) -> None:
            bar.update(n)
            stop.check()

        with self.bar(cfg.demo_episodes, "episode", f"demonstrations, {g.n_robots} robots") as bar:
            demos = collect_demos(self.world, g.n_robots, cfg.demo_episodes, cfg.n_envs, rng, tick, t_prev,
                                  self.algo.device, cfg.critic_obs, kind=cfg.demo_policy)
        self.log(f"demonstrations: {int((demos.filled > 0).sum())} episodes of the {cfg.demo_policy} with "
                 f"{g.n_robots} robots in {time.perf_counter() - t0:.0f} s")
        return demos

    def clone(self, rng: np.random.Generator, shares: list[int], stop: StopRequest, export) -> float:
        """Behaviour cloning of the actor (and its target); evaluate, keep as policy_bc.npz and as the best
        so far (RL must beat it). Returns the clone's evaluation return."""
        cfg, algo = self.cfg, self.algo
        t0 = time.perf_counter()

        def tick(k: int, loss: float) -> None:
            bar.update(1)
            stop.check()

        with self.bar(cfg.bc_updates, "update", "behaviour cloning") as bar:
            loss = bc_pretrain(algo, [g.demos for g in self.groups], shares, cfg.bc_updates, cfg.bc_lr, rng, tick)
        algo.actor_target.load_state_dict(algo.actor.state_dict())
        bc_s = time.perf_counter() - t0
        demo_m = {ev.n_robots: metrics_row(ev(demonstrator(self.world, kind=cfg.demo_policy))) for ev in self.evaluators}
        bc_m = {ev.n_robots: metrics_row(ev(LearnerPolicy(algo, self.world))) for ev in self.evaluators}
        mean = {k: float(np.mean([m[k] for m in bc_m.values()])) for k in next(iter(bc_m.values()))}
        first = next(iter(bc_m))
        info = {"demo_policy": cfg.demo_policy,
                "demo_episodes": int(sum((g.demos.filled > 0).sum() for g in self.groups)),
                "bc_updates": cfg.bc_updates, "bc_loss": loss, "bc_s": round(bc_s, 1),
                "eval_demonstrator": finite_or_none(demo_m[first]), "eval_after_bc": finite_or_none(bc_m[first]),
                "per_size": {str(M): {"demonstrator": finite_or_none(demo_m[M]), "after_bc": finite_or_none(bc_m[M])}
                             for M in bc_m}}
        write_atomic(self.run_dir / "demos.json", json.dumps(info, indent=2, sort_keys=True) + "\n")
        export("policy_bc.npz", mean)
        export("policy_best.npz", mean)
        primary, primary_label = success_panel(cfg.task_spec())
        sizes = ", ".join(f"{M} robots {bc_m[M][primary]:.3f} (demonstrator {demo_m[M][primary]:.3f})" for M in bc_m)
        self.log(f"behaviour cloning: loss {loss:.4f} in {bc_s:.0f} s; evaluation return {mean['eval_return']:.1f}, "
                 f"{primary_label} {sizes}")
        return mean["eval_return"]

    def critic(self, rng: np.random.Generator, shares: list[int], demo_shares: list[int], stop: StopRequest) -> None:
        """Critic-only updates on demonstration samples: Q of the (cloned) actor before the actor may move."""
        cfg, algo = self.cfg, self.algo
        t0 = time.perf_counter()
        qs = []
        with self.bar(cfg.critic_pretrain, "update", "critic on demonstrations") as bar:
            for _ in range(cfg.critic_pretrain):
                parts = [(algo.sample(g.demos, n + nd, rng), False) for g, n, nd in zip(self.groups, shares, demo_shares)]
                qs.append(algo.update_parts(parts, train_actor=False).q_mean)
                bar.update(1)
                stop.check()
        self.log(f"critic pre-training: {cfg.critic_pretrain} updates on demonstrations in "
                 f"{time.perf_counter() - t0:.0f} s, mean Q {np.mean(qs[-100:]):.1f}")
