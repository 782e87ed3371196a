"""``train_es``: the evolution-strategies run — clone the demonstrator, then ascend the task's final success.

Read top to bottom: seeding (one ``SeedSequence``; every generation's perturbations and episodes are
drawn from its own child ``(seed, generation)``, so a resumed run needs only the generation index,
the weights and Adam's moments to continue exactly), the actor (MAGDDPG's MLP over the T_prev
history, so artifacts, export and evaluation are the ones of every other run), behaviour cloning of
the searcher on every swarm size (:mod:`learn.demos`), then the generations (:mod:`learn.es`). Every
``eval_every`` generations the current weights play fixed evaluation episodes of ``eval_steps``
steps at every swarm size; the best mean of the task's primary metric over the sizes is ``policy_best.npz``.

The run directory is the one of :mod:`learn.rundir` (config.json, world.json, metrics.csv,
learning_curve.png, checkpoint.pt, policy_bc/best/last.npz, summary.json; with ``keep_evaluated`` also
generations/gen_NNN.npz for every evaluation). SIGINT / SIGTERM stop
after the current generation with a checkpoint; the CLI exits 130 / 143.
"""
from __future__ import annotations

import dataclasses
import datetime
import functools
import json
import math
import os
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from kiloforge.io import write_atomic
from kiloforge.progress import progress_bar

from .checkpoint import Checkpointer
from .config import ConfigError, ESConfig, TrainConfig, randomisation
from .demos import bc_pretrain, collect_demos, demonstrator
from .es import Adam, PopulationMLP, centred_ranks, es_direction, rollout_population
from .es_pool import child as _child
from .es_pool import blocks, noise, worker_pool
from .evaluate import Evaluator, LearnerPolicy, evaluate_sizes, metrics_row, success_panel
from .interrupt import Interrupted, StopRequest
from .magddpg import MAGDDPG
from .rundir import KEPT_DIR, Counters, RunResult, check_resumable, finite_or_none, git_hash, prepare_run_dir, \
    rows_to_csv, write_summary
from .speed import set_threads, tune_allocator

CHECKPOINT_VERSION = 1
DEMO_ENVS = 24  #: demonstrator envs stepped together per swarm size


def actor_algo(cfg: ESConfig, world) -> MAGDDPG:
    """The MLP actor (in a MAGDDPG, for its artifact, cloning loss and acting)."""
    tc = TrainConfig(world=cfg.world, n_robots=(min(cfg.n_robots),), t_prev=cfg.t_prev,
                     actor_hidden=cfg.actor_hidden, critic_hidden=(1,))
    return MAGDDPG.from_config(tc, world)


def get_theta(algo: MAGDDPG) -> torch.Tensor:
    return torch.nn.utils.parameters_to_vector(algo.actor.net.parameters()).detach().double().clone()


def set_theta(algo: MAGDDPG, theta: torch.Tensor) -> None:
    with torch.no_grad():
        torch.nn.utils.vector_to_parameters(theta.float(), algo.actor.net.parameters())


def train_es(cfg: ESConfig, run_dir: str | os.PathLike, resume: bool = False, progress: bool = True,
             log: Callable[[str], None] = print) -> RunResult:
    """Run ``cfg`` into ``run_dir`` (``resume`` continues its checkpoint); returns counters and why it stopped.

    The population is evaluated in this process (``cfg.workers`` 1) or on Ray workers (:mod:`learn.es_pool`,
    started before anything is written, so a cluster that cannot be reached leaves nothing behind)."""
    cfg.validate()
    with worker_pool(cfg.workers, cfg.ray_address, cfg.threads, log) as pool:
        if pool.workers > 1 or cfg.ray_address:
            sizes = sorted({b - a for a, b in blocks(2 * cfg.pairs, pool.workers)})
            log(f"evaluating the population on {pool.workers} Ray workers"
                + (f" of the cluster at {cfg.ray_address}" if cfg.ray_address else "")
                + f", in blocks of {'–'.join(map(str, sizes))} members (docs/distributed.md: how large a block pays)")
        return _train_es(cfg, run_dir, resume, progress, log, pool)


def _train_es(cfg: ESConfig, run_dir: str | os.PathLike, resume: bool, progress: bool, log: Callable[[str], None],
              pool) -> RunResult:
    world, eval_world = cfg.world_config(), cfg.eval_world()
    set_threads(cfg.threads)
    tune_allocator()
    randomise = [randomisation(name) for name in cfg.size_randomises()]  # per swarm size (None: nominal)

    # --- seeding -------------------------------------------------------------------------------
    ss_init, ss_demo, ss_gen, ss_eval = np.random.SeedSequence(cfg.seed).spawn(4)
    torch.manual_seed(int(ss_init.generate_state(1, np.uint64)[0]))
    eval_seed = int(ss_eval.generate_state(1, np.uint32)[0])

    algo = actor_algo(cfg, world)
    init = None if resume else init_policy_of(cfg, algo, world)  # refused before anything is written
    run_dir = Path(run_dir)
    resume = prepare_run_dir(run_dir, resume, log)
    if not resume and init is None:  # --resume of a run that had no checkpoint yet: a fresh start
        init = init_policy_of(cfg, algo, world)
    ckpt = Checkpointer(run_dir)
    pop = PopulationMLP.of(algo.actor.net)
    task = cfg.task_spec()
    evaluators = [Evaluator(eval_world, M, cfg.eval_episodes, eval_seed, task=task) for M in cfg.n_robots]
    primary, primary_label = success_panel(task)
    weights = cfg.weights()
    c = Counters()
    result = RunResult(run_dir, c, "done")
    theta = get_theta(algo)
    adam = Adam(pop.n_params, cfg.lr)
    gen = 0
    init_hash = ""  # the hash of cfg.init_policy, for the provenance (kept in the checkpoint)

    def export(name: str, row: dict) -> None:
        from kiloforge.policies import save_policy

        prov = {"trainer": "kiloforge.learn ES", "config": cfg.to_dict(), "seed": cfg.seed, "git": git_hash(),
                "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
                "torch": torch.__version__, "trained_robots": list(cfg.n_robots), "generations": gen,
                "env_steps": c.env_steps, "wall_s": round(c.wall_s, 1), "eval": finite_or_none(dict(row))}
        if cfg.init_policy:
            prov["init_policy_hash"] = init_hash
        save_policy(dataclasses.replace(algo.artifact(world, prov), task=cfg.task_spec().ref), run_dir / name)

    def evaluate() -> dict:
        set_theta(algo, theta)
        mean, per_size = evaluate_sizes(evaluators, lambda: LearnerPolicy(algo, eval_world))
        return mean | per_size

    def log_row(metrics: dict, fitness: float) -> dict:
        row = {"env_steps": c.env_steps, "episodes": c.episodes, "updates": gen, "wall_s": round(c.wall_s, 2),
               **metrics, "train_return": float("nan"), "critic_loss": float("nan"), "q_mean": float("nan"),
               "env_steps_per_s": c.env_steps / c.env_s if c.env_s > 0 else float("nan"),
               "updates_per_s": float("nan"), "generation": gen, "fitness": fitness}
        c.rows.append(row)
        c.evals += 1
        export("policy_last.npz", row)
        if cfg.keep_evaluated:
            (run_dir / KEPT_DIR).mkdir(exist_ok=True)
            export(f"{KEPT_DIR}/gen_{gen:03d}.npz", row)
        if row[primary] > c.best_return:  # ES selects on the task's primary metric (final success), not return
            c.best_return = row[primary]
            export("policy_best.npz", row)
        write_atomic(run_dir / "metrics.csv", rows_to_csv(c.rows, task))
        from .plots import plot_learning_curves

        plot_learning_curves({run_dir.name: c.rows}, run_dir / "learning_curve.png", success=(primary, primary_label),
                             title=f"ES, {'/'.join(map(str, cfg.n_robots))} robots, {algo.describe()} ({cfg.world} world)")
        return row

    def save() -> None:
        t0 = time.perf_counter()
        c.wall_s = wall_at_start + (time.perf_counter() - session_start)
        ckpt.save({"version": CHECKPOINT_VERSION, "algorithm": cfg.algorithm, "config": cfg.to_dict(),
                   "es_generation": gen, "init_policy_hash": init_hash, "theta": theta, "adam": adam.state_dict(),
                   "counters": vars(c)}, [])
        c.checkpoint_s += time.perf_counter() - t0

    stop = StopRequest()
    bar = None
    session_start = time.perf_counter()
    wall_at_start = 0.0
    with stop:
        try:
            if resume:
                state = ckpt.load([])
                if state.get("version") != CHECKPOINT_VERSION or state.get("algorithm") != cfg.algorithm:
                    raise ConfigError(f"'{ckpt.path}' is not an ES checkpoint of version {CHECKPOINT_VERSION}")
                check_resumable(state["config"], cfg)
                gen = int(state["es_generation"])
                init_hash = str(state.get("init_policy_hash", ""))
                theta = state["theta"].double()
                adam.load_state_dict(state["adam"])
                c = result.counters = Counters(**state["counters"])
                log(f"resumed {run_dir} at generation {gen}")
            else:
                ckpt.clean()
                write_atomic(run_dir / "config.json", cfg.to_json() + "\n")
                write_atomic(run_dir / "world.json", json.dumps(world.to_dict(), indent=2, sort_keys=True) + "\n")
                if init is not None:
                    load_weights(algo, init)
                    theta, init_hash = get_theta(algo), init.hash
                    log(f"starting from {cfg.init_policy} (policy hash {init.hash[:12]})")
                elif cfg.init_bias:
                    set_output_bias(algo, cfg.init_bias)
                    theta = get_theta(algo)
                    log(f"starting from random weights with the output bias at {cfg.init_bias:g}")
                elif cfg.demo_policy != "none":
                    clone(cfg, world, algo, ss_demo, stop, progress, log)
                    theta = get_theta(algo)
                    export("policy_bc.npz", {})
                    bc = evaluate()
                    teacher = demonstrator(eval_world, cfg.demo_stop_dist, cfg.demo_policy)
                    demo = {M: metrics_row(ev(teacher))[primary] for M, ev in zip(cfg.n_robots, evaluators)}
                    write_atomic(run_dir / "demos.json", json.dumps(finite_or_none(
                        {"clone": bc, f"demonstrator_{task.primary_metric}": demo}), indent=2, sort_keys=True) + "\n")
                    log(f"behaviour clone: {primary_label} {bc[primary]:.3f} "
                        f"(demonstrator {np.mean(list(demo.values())):.3f})")
                log_row(evaluate(), float("nan"))
                save()
            if gen < cfg.generations:
                pool.warm(task_fitness(cfg, world, pop, randomise), theta)  # Ray workers: start-up, not generations
            wall_at_start = c.wall_s
            session_start = time.perf_counter()
            gen_at_start, episodes_at_start, session_gen_s = gen, c.episodes, 0.0  # this session's rates
            if progress:
                bar = progress_bar(total=cfg.generations, initial=gen, unit="gen", dynamic_ncols=True,
                                   desc=run_dir.name[:40], max_seconds=60 * cfg.max_minutes, elapsed=wall_at_start)
            while gen < cfg.generations:
                stop.check()
                if cfg.max_minutes and wall_at_start + time.perf_counter() - session_start >= 60 * cfg.max_minutes:
                    result.stopped = "time"
                    if c.rows and c.rows[-1]["generation"] != gen:  # the weights it stops with are evaluated
                        log_row(evaluate(), float("nan"))
                        save()
                    break
                t0 = time.perf_counter()
                fitness, utility = generation(cfg, world, pop, theta, _child(ss_gen, gen), weights, randomise, c, stop,
                                              pool)
                eps = fitness.pop("eps")
                theta = adam.step(theta, es_direction(utility, eps, cfg.sigma))
                gen += 1
                c.env_s += time.perf_counter() - t0
                session_gen_s += time.perf_counter() - t0
                c.wall_s = wall_at_start + (time.perf_counter() - session_start)
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix_str(f"fitness {fitness['mean']:.3f}  {(gen - gen_at_start) / session_gen_s:.2f} gen/s  "
                                        f"{(c.episodes - episodes_at_start) / session_gen_s:.0f} member-episodes/s",
                                        refresh=True)
                if gen % cfg.eval_every == 0 or gen == cfg.generations:
                    t1 = time.perf_counter()
                    row = log_row(evaluate(), fitness["mean"])
                    c.eval_s += time.perf_counter() - t1
                    msg = f"generation {gen}: {primary_label} {row[primary]:.3f} (fitness {fitness['mean']:.3f})"
                    if bar is not None:
                        bar.write(msg)
                    else:
                        log(msg)
                    save()
        except (Interrupted, KeyboardInterrupt) as e:
            result.stopped = "interrupted"
            result.signal = e.signum if isinstance(e, Interrupted) else 2
            if ckpt.exists():
                save()
                log("interrupted: checkpoint written; --resume continues from it")
            else:
                log("interrupted before the first checkpoint; --resume restarts the run")
        finally:
            if bar is not None:
                bar.close()
    if result.stopped != "interrupted" and ckpt.exists():
        save()
    c.wall_s = wall_at_start + (time.perf_counter() - session_start)
    write_summary(run_dir, cfg, c, result.stopped,
                  {"generations": gen, "generation_s": round(c.env_s, 3), "workers": pool.workers,
                   "workers_start_s": round(pool.start_s, 2)})
    return result


def init_policy_of(cfg: ESConfig, algo: MAGDDPG, world):
    """The MLP artifact ``cfg.init_policy`` (None when empty); a one-line ConfigError unless it loads and is
    an MLP of the same world, history length, widths and activations as this run's actor ``algo``."""
    if not cfg.init_policy:
        return None
    from kiloforge.errors import PolicyError
    from kiloforge.policies import load_policy

    try:
        p = load_policy(cfg.init_policy)
    except (PolicyError, OSError) as e:
        raise ConfigError(f"init_policy: {e}") from None
    ours = algo.artifact(world, {})
    same_kind = p.kind == ours.kind
    # the episode length is how long training plays, not part of the world a policy acts in
    def same_length(w):
        return w.to_dict() | {"episode_steps": world.episode_steps}

    what = {"kind": (p.kind, ours.kind), "world": (same_length(p.world), world.to_dict()), "t_prev": (p.t_prev, ours.t_prev),
            "layers": (p.layer_sizes, ours.layer_sizes) if same_kind else (0, 0),
            "activations": (list(p.activations), list(ours.activations)) if same_kind else (0, 0)}
    diff = [k for k, (x, y) in what.items() if x != y]
    if diff:
        raise ConfigError(f"init_policy '{cfg.init_policy}' differs from this run in {', '.join(diff)}: "
                          f"it must be an MLP of the {world.name} world with t_prev {cfg.t_prev} and hidden "
                          f"{list(cfg.actor_hidden)}")
    return p


def set_output_bias(algo: MAGDDPG, bias: float) -> None:
    """Every output unit's bias of the actor's last layer set to ``bias`` (the other weights stay as drawn)."""
    out = [m for m in algo.actor.net if isinstance(m, torch.nn.Linear)][-1]
    with torch.no_grad():
        out.bias.fill_(bias)


def load_weights(algo: MAGDDPG, policy) -> None:
    """Copy an MLP artifact's weights into the actor."""
    linears = [m for m in algo.actor.net if isinstance(m, torch.nn.Linear)]
    with torch.no_grad():
        for lin, w, b in zip(linears, policy.weights, policy.biases, strict=True):
            lin.weight.copy_(torch.tensor(np.array(w, np.float32)))
            lin.bias.copy_(torch.tensor(np.array(b, np.float32)))


def clone(cfg: ESConfig, world, algo: MAGDDPG, ss_demo: np.random.SeedSequence, stop: StopRequest,
          progress: bool, log) -> float:
    """Behaviour cloning of the demonstrator on every swarm size (equal robot-steps per size)."""
    rng = np.random.default_rng(ss_demo)
    demos = []
    for M in cfg.n_robots:
        episodes = math.ceil(cfg.demo_robot_episodes / M)
        demos.append(collect_demos(world, M, episodes, min(episodes, DEMO_ENVS), rng, t_prev=cfg.t_prev,
                                   stop_dist=cfg.demo_stop_dist, kind=cfg.demo_policy))
        stop.check()
    shares = [max(1, cfg.bc_batch // (len(cfg.n_robots) * M)) for M in cfg.n_robots]
    bar = None
    if progress:
        bar = progress_bar(total=cfg.bc_updates, unit="step", desc="behaviour cloning", dynamic_ncols=True, leave=False)

    def tick(k: int, loss: float) -> None:
        stop.check()
        if bar is not None:
            bar.update(1)
            if k % 100 == 0:
                bar.set_postfix_str(f"loss {loss:.4f}")

    try:
        loss = bc_pretrain(algo, demos, shares, cfg.bc_updates, cfg.bc_lr, rng, tick)
    finally:
        if bar is not None:
            bar.close()
    log(f"behaviour cloning: {cfg.bc_updates} steps, final loss {loss:.4f}")
    return loss


@dataclasses.dataclass(frozen=True)
class TaskFitness:
    """The ES fitness of a task (a :class:`learn.es_pool.Fitness`): part i is swarm size ``n_robots[i]``, a
    member's mean final success of ``task`` (a :func:`sim.tasks.get_task` name, resolved where it runs; a
    ``file.py:Class`` task must be at the same path on every worker) over that size's ``episodes[i]``
    episodes in the task's world for that size (``Task.world_for``), episode e seeded by the generation's child
    ``(1 + i, e)`` (common random numbers)."""

    task: str
    pop: PopulationMLP
    world: object
    t_prev: int
    n_robots: tuple[int, ...]
    randomise: tuple  # per swarm size: its domain randomisation or None
    episodes: tuple[int, ...]

    @property
    def parts(self) -> int:
        return len(self.n_robots)

    def __call__(self, members: torch.Tensor, part: int, seed: np.random.SeedSequence) -> np.ndarray:
        seeds = [_child(seed, 1 + part, e) for e in range(self.episodes[part])]
        M = self.n_robots[part]
        res = rollout_population(self.pop, members, self.task_spec.world_for(self.world, M), M, seeds, self.t_prev,
                                 self.randomise[part], self.task_spec)
        return res.final_success.mean(axis=1)

    @functools.cached_property
    def task_spec(self):
        from sim.tasks import get_task

        return get_task(self.task)


def task_fitness(cfg: ESConfig, world, pop: PopulationMLP, randomise: list) -> TaskFitness:
    """The fitness of ``cfg``'s task on its swarm sizes (``randomise``: each size's domain randomisation or None)."""
    return TaskFitness(cfg.task, pop, world, cfg.t_prev, tuple(cfg.n_robots), tuple(randomise),
                       tuple(cfg.size_episode_counts()))


def generation(cfg: ESConfig, world, pop: PopulationMLP, theta: torch.Tensor, ss: np.random.SeedSequence,
               weights: list[float], randomise: list, c: Counters, stop: StopRequest, pool) -> tuple[dict, np.ndarray]:
    """One generation's antithetic population on every swarm size (``randomise``: each size's domain
    randomisation or None), evaluated by ``pool`` (:mod:`learn.es_pool`): fitness summary and utilities (2 · pairs,).

    A stop request abandons the generation (the weights stay those of the last one)."""
    eps = noise(ss, cfg.pairs, pop.n_params)
    f_parts = pool.evaluate(task_fitness(cfg, world, pop, randomise), theta, cfg.sigma, cfg.pairs, ss, stop)  # (2 pairs, sizes)
    utility = sum(w * centred_ranks(f_parts[:, i]) for i, w in enumerate(weights))
    fit = sum(w * f_parts[:, i] for i, w in enumerate(weights))
    episodes = 2 * cfg.pairs * sum(cfg.size_episode_counts())
    c.episodes += episodes
    c.env_steps += episodes * world.episode_steps
    return {"mean": float(fit.mean()), "max": float(fit.max()), "eps": eps}, utility
