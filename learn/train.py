"""The MAGDDPG training loop (thesis Algorithm 4), run directories, checkpoints and artifacts.

Read top to bottom: seeding, environment and networks, then one loop over batches of
``n_envs`` synchronised episodes. Each step every robot acts on its own history with
Ornstein-Uhlenbeck noise, the joint transition goes to the replay memory, and after the warm-up
``updates_per_step`` gradient updates are made per collected transition. At episode ends the
trainer evaluates (every ``eval_every`` transitions), logs, checkpoints and exports the policy.

A run directory holds::

    config.json          the TrainConfig (the world preset it names is in world.json)
    world.json           the WorldConfig trained in
    metrics.csv          one row per evaluation (see METRIC_COLUMNS)
    learning_curve.png   evaluation return and final coverage over transitions
    checkpoint.pt        everything needed to resume exactly (written atomically)
    policy_best.npz      the actor with the best evaluation return (kiloforge.artifact format)
    policy_last.npz      the latest actor
    summary.json         final numbers: best evaluation, wall time, updates/s, env steps/s
"""
from __future__ import annotations

import csv
import io
import json
import math
import os
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from kiloforge.actors.mlp import MLPPolicy
from kiloforge.io import write_atomic
from kiloforge.policies import save_policy
from sim.config import ACTION_DIM
from sim.env import SwarmEnv
from sim.history import History

from .checkpoint import load_checkpoint, save_checkpoint
from .config import ConfigError, TrainConfig
from .evaluate import Evaluator, metrics_row
from .augment import PhantomNeighbours
from .magddpg import MAGDDPG
from .noise import OUNoise
from .replay import EpisodeReplay

TASK = "coop_loc"  #: task name in run names (the thesis's cooperative localisation)
CHECKPOINT_VERSION = 1
PLOT_EVERY_S = 60.0  #: redraw learning_curve.png at most this often (and at the end): plotting is slow
METRIC_COLUMNS = ("env_steps", "episodes", "updates", "wall_s", "eval_return", "eval_return_std",
                  "eval_final_coverage", "eval_mean_coverage", "eval_time_to_find", "eval_found_rate",
                  "train_return", "critic_loss", "q_mean", "env_steps_per_s", "updates_per_s")


def run_name(cfg: TrainConfig) -> str:
    """CleanRL-style run name: task__experiment__seed__unixtime."""
    return f"{TASK}__{cfg.exp_name}__{cfg.seed}__{int(time.time())}"


def git_hash() -> str:
    """The commit of the code that trains (``unknown`` outside a git checkout)."""
    try:
        out = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=Path(__file__).parent,
                             capture_output=True, text=True, timeout=5)
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


@dataclass
class Counters:
    """Progress of a run (all of it goes into checkpoints)."""

    env_steps: int = 0  # transitions collected (summed over envs)
    episodes: int = 0  # episodes finished (summed over envs)
    updates: int = 0  # gradient updates made
    update_debt: float = 0.0  # fractional updates owed (updates_per_step * transitions so far)
    next_eval: int = 0  # evaluate at the first episode end with env_steps >= this
    evals: int = 0
    best_return: float = -math.inf
    wall_s: float = 0.0  # wall clock spent in this run, over all sessions
    env_s: float = 0.0  # of which: acting and stepping the environments
    update_s: float = 0.0  # of which: gradient updates
    rows: list = field(default_factory=list)  # metrics.csv rows


@dataclass
class RunResult:
    run_dir: Path
    counters: Counters
    stopped: str  # "done", "time" or "interrupted"


def train(cfg: TrainConfig, run_dir: str | os.PathLike, resume: bool = False, progress: bool = True,
          log: Callable[[str], None] = print) -> RunResult:
    """Train MAGDDPG with ``cfg``, writing to ``run_dir``; ``resume`` continues from its checkpoint."""
    cfg.validate()
    run_dir = Path(run_dir)
    prepare_run_dir(run_dir, resume)
    world = cfg.world_config()
    M, B, T = cfg.n_robots, cfg.n_envs, world.episode_steps
    history_dim, state_dim = world.history_dim(cfg.t_prev), world.state_dim(M)

    # --- seeding: one SeedSequence, one stream per consumer; no global NumPy RNG -------------
    torch.set_num_threads(cfg.threads)
    ss_init, ss_env, ss_noise, ss_replay, ss_eval, ss_aug = np.random.SeedSequence(cfg.seed).spawn(6)
    torch.manual_seed(int(ss_init.generate_state(1, np.uint64)[0]))
    env_rng = np.random.default_rng(ss_env)  # episode reset seeds
    noise_rng = np.random.default_rng(ss_noise)
    sample_rng = np.random.default_rng(ss_replay)
    aug_rng = np.random.default_rng(ss_aug)  # phantom neighbours (off unless phantom_neighbours > 0)
    eval_seed = int(ss_eval.generate_state(1, np.uint32)[0])

    # --- environments, networks, memory -------------------------------------------------------
    env = SwarmEnv(world, n_envs=B, n_robots=M, seed=int(env_rng.integers(2 ** 31)))
    agent = MAGDDPG(history_dim, state_dim, M, cfg.actor_hidden, cfg.critic_hidden, cfg.gamma, cfg.tau,
                    cfg.lr_actor, cfg.lr_critic, cfg.reward_scale)
    replay = EpisodeReplay(cfg.replay_size, T, M, world.tuple_dim, state_dim, cfg.t_prev)
    noise = OUNoise((B, M, ACTION_DIM), cfg.noise_theta, cfg.noise_sigma, cfg.noise_mu, noise_rng)
    history = History(cfg.t_prev, world.obs_dim)
    phantoms = PhantomNeighbours(world, cfg.phantom_neighbours, aug_rng)
    evaluator = Evaluator(world, M, cfg.t_prev, cfg.eval_episodes, eval_seed)
    c = Counters()

    if resume:
        ck = load_checkpoint(run_dir / "checkpoint.pt")
        check_resumable(ck, cfg)
        agent.load_state_dict(ck["agent"])
        replay.load_state_dict(ck["replay"])
        env_rng.bit_generator.state = ck["rng"]["env"]
        noise_rng.bit_generator.state = ck["rng"]["noise"]
        sample_rng.bit_generator.state = ck["rng"]["replay"]
        aug_rng.bit_generator.state = ck["rng"]["augment"]
        torch.set_rng_state(ck["rng"]["torch"])
        c = Counters(**ck["counters"])
        log(f"resumed {run_dir} at {c.env_steps} transitions, {c.updates} updates")
    else:
        write_atomic(run_dir / "config.json", cfg.to_json() + "\n")
        write_atomic(run_dir / "world.json", json.dumps(world.to_dict(), indent=2, sort_keys=True) + "\n")

    def snapshot() -> dict:
        return {"version": CHECKPOINT_VERSION, "config": cfg.to_dict(), "agent": agent.state_dict(),
                "replay": replay.state_dict(),
                "rng": {"env": env_rng.bit_generator.state, "noise": noise_rng.bit_generator.state,
                        "replay": sample_rng.bit_generator.state, "augment": aug_rng.bit_generator.state,
                        "torch": torch.get_rng_state()},
                "counters": vars(c)}

    def export(name: str, metrics: dict) -> None:
        save_policy(actor_policy(agent, cfg, world, c, metrics), run_dir / name)

    total_steps = cfg.total_episodes * T
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total_steps, initial=min(c.env_steps, total_steps), unit="step", dynamic_ncols=True,
                   desc=run_dir.name[:40], smoothing=0.05)
    session_start = time.perf_counter()
    wall_at_start = c.wall_s
    stopped = "done"
    last_plot = -math.inf
    train_returns: list[float] = []
    losses: list[tuple[float, float]] = []
    try:
        while c.episodes < cfg.total_episodes:
            # ---- one batch of B synchronised episodes (Algorithm 4, "for episode") ----------
            t0 = time.perf_counter()
            obs, _ = env.reset(seed=int(env_rng.integers(2 ** 31)))
            noise.reset()
            phantoms.reset(B)
            h = history.reset(phantoms(obs))  # (B, M, history_dim): (a_0 = 0, o_1) repeated
            replay.begin(history.buf[:, :, 0], env.state())
            learning = c.episodes >= cfg.warmup_episodes
            ep_return = np.zeros(B)
            upd_time = 0.0
            for t in range(T):
                a = np.clip(agent.act(h) + noise.sample(), 0.0, 1.0).astype(np.float32)  # (B, M, 2)
                obs, reward, _, truncated, _ = env.step(a)
                obs = phantoms(obs)
                h = history.push(a, obs)
                effort = np.mean(np.sum(a * a, axis=-1), axis=-1)  # (B,) (1/M) Σ_i ||a_i||²
                r_learn = reward - world.reward_scale * cfg.extra_action_penalty * effort
                replay.add(np.concatenate([a, obs], axis=-1), env.state(), r_learn)
                ep_return += reward
                c.env_steps += B
                if learning:
                    c.update_debt += B * cfg.updates_per_step
                    u0 = time.perf_counter()
                    while c.update_debt >= 1.0:
                        st = agent.update(replay.sample(cfg.batch_size, sample_rng))
                        losses.append((st.critic_loss, st.q_mean))
                        c.update_debt -= 1.0
                        c.updates += 1
                    upd_time += time.perf_counter() - u0
                if bar is not None:
                    bar.update(B)
            assert np.all(truncated), "the env did not truncate after episode_steps steps"
            c.episodes += B
            train_returns.extend(ep_return.tolist())
            elapsed = time.perf_counter() - t0
            c.update_s += upd_time
            c.env_s += elapsed - upd_time
            c.wall_s = wall_at_start + (time.perf_counter() - session_start)

            # ---- evaluation, logging, checkpoint ----------------------------------------------
            over_time = cfg.max_minutes > 0 and (time.perf_counter() - session_start) >= 60 * cfg.max_minutes
            last = c.episodes >= cfg.total_episodes or over_time
            if c.env_steps >= c.next_eval or last:
                plot = last or time.perf_counter() - last_plot >= PLOT_EVERY_S
                evaluate_and_log(cfg, agent, evaluator, c, train_returns, losses, run_dir, export, log, bar, plot)
                last_plot = time.perf_counter() if plot else last_plot
                train_returns, losses = [], []
                while c.next_eval <= c.env_steps:
                    c.next_eval += cfg.eval_every
                if last or (cfg.checkpoint_every and c.evals % cfg.checkpoint_every == 0):
                    c.wall_s = wall_at_start + (time.perf_counter() - session_start)
                    save_checkpoint(snapshot(), run_dir / "checkpoint.pt")
            if over_time:
                stopped = "time"
                break
    except KeyboardInterrupt:
        stopped = "interrupted"
        log("interrupted: policy_last.npz holds the current actor; --resume continues from the last checkpoint")
        export("policy_last.npz", c.rows[-1] if c.rows else {})
    finally:
        if bar is not None:
            bar.close()
    c.wall_s = wall_at_start + (time.perf_counter() - session_start)
    write_summary(run_dir, cfg, c, stopped)
    return RunResult(run_dir, c, stopped)


def evaluate_and_log(cfg: TrainConfig, agent: MAGDDPG, evaluator: Evaluator, c: Counters,
                     train_returns: list[float], losses: list, run_dir: Path, export, log, bar,
                     plot: bool = True) -> None:
    """Evaluate deterministically, append a metrics row, export best/last, redraw the curve when ``plot``."""
    from .plots import plot_learning_curves

    metrics = metrics_row(evaluator(agent.act))
    row = {"env_steps": c.env_steps, "episodes": c.episodes, "updates": c.updates, "wall_s": round(c.wall_s, 2),
           **metrics,
           "train_return": float(np.mean(train_returns)) if train_returns else float("nan"),
           "critic_loss": float(np.mean([x[0] for x in losses])) if losses else float("nan"),
           "q_mean": float(np.mean([x[1] for x in losses])) if losses else float("nan"),
           "env_steps_per_s": c.env_steps / c.env_s if c.env_s > 0 else float("nan"),
           "updates_per_s": c.updates / c.update_s if c.update_s > 0 else float("nan")}
    c.rows.append(row)
    c.evals += 1
    export("policy_last.npz", row)
    if row["eval_return"] > c.best_return:
        c.best_return = row["eval_return"]
        export("policy_best.npz", row)
    write_atomic(run_dir / "metrics.csv", rows_to_csv(c.rows))
    if plot:
        plot_learning_curves({run_dir.name: c.rows}, run_dir / "learning_curve.png",
                             title=f"MAGDDPG, {cfg.n_robots} robots, T_prev {cfg.t_prev} ({cfg.world} world)")
    msg = (f"return {row['eval_return']:.1f}  final cov {row['eval_final_coverage']:.2f}  "
           f"find {row['eval_time_to_find']:.0f}")
    if bar is not None:
        bar.set_postfix_str(f"{msg}  upd/s {row['updates_per_s']:.0f}", refresh=True)
    else:
        log(f"[{c.env_steps} steps, {c.updates} updates, {c.wall_s:.0f} s] {msg}")


def rows_to_csv(rows: list[dict]) -> str:
    """CSV of metric rows: METRIC_COLUMNS, then any extra columns a trainer adds (e.g. MAGRDPG's bc_pass)."""
    buf = io.StringIO()
    extra = list(dict.fromkeys(k for r in rows for k in r if k not in METRIC_COLUMNS))  # first-seen order
    w = csv.DictWriter(buf, fieldnames=list(METRIC_COLUMNS) + extra, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    return buf.getvalue()


def read_metrics(run_dir: str | os.PathLike) -> list[dict]:
    """metrics.csv of a run directory as a list of float dicts."""
    path = Path(run_dir) / "metrics.csv"
    if not path.is_file():
        raise ConfigError(f"'{run_dir}' has no metrics.csv; is it a training run directory?")
    with open(path, newline="") as f:
        return [{k: float(v) if v not in ("", None) else float("nan") for k, v in r.items()}
                for r in csv.DictReader(f)]


def actor_policy(agent: MAGDDPG, cfg: TrainConfig, world, c: Counters, metrics: dict) -> MLPPolicy:
    """The current actor as a :class:`kiloforge.actors.mlp.MLPPolicy` with provenance."""
    layers = agent.actor.layers()
    provenance = {
        "trainer": "kiloforge.learn MAGDDPG", "config": cfg.to_dict(), "seed": cfg.seed,
        "git": git_hash(), "torch": torch.__version__, "trained_robots": cfg.n_robots,
        "env_steps": c.env_steps, "updates": c.updates, "wall_s": round(c.wall_s, 1),
        "eval": finite_or_none(dict(metrics)),
    }
    return MLPPolicy(weights=[w for w, _, _ in layers], biases=[b for _, b, _ in layers],
                     activations=[a for _, _, a in layers], t_prev=cfg.t_prev, world=world, provenance=provenance)


def prepare_run_dir(run_dir: Path, resume: bool) -> None:
    """Create the run directory; refuse to overwrite a run, or to resume one that has no checkpoint."""
    if resume:
        if not (run_dir / "checkpoint.pt").is_file():
            raise ConfigError(f"cannot resume: '{run_dir}' has no checkpoint.pt")
        return
    if (run_dir / "config.json").exists() or (run_dir / "checkpoint.pt").exists():
        raise ConfigError(f"'{run_dir}' already holds a run; use --resume to continue it or choose another --out")
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"cannot create run directory '{run_dir}': {e.strerror or e}") from None


#: fields that may differ between a checkpoint and a resumed run (budgets and speed knobs)
RESUME_MAY_CHANGE = ("episodes", "max_minutes", "threads", "checkpoint_every")


def check_resumable(ck: dict, cfg: TrainConfig) -> None:
    if ck.get("version") != CHECKPOINT_VERSION:
        raise ConfigError(f"checkpoint version {ck.get('version')} is not supported (expected {CHECKPOINT_VERSION})")
    saved = ck["config"]
    now = cfg.to_dict()
    diff = sorted(k for k in now if k not in RESUME_MAY_CHANGE and saved.get(k) != now[k])
    if diff:
        raise ConfigError(f"cannot resume with a different {', '.join(diff)}; only "
                          f"{', '.join(RESUME_MAY_CHANGE)} may change")


def write_summary(run_dir: Path, cfg: TrainConfig, c: Counters, stopped: str) -> None:
    best = max(c.rows, key=lambda r: r["eval_return"]) if c.rows else {}
    summary = {
        "stopped": stopped, "env_steps": c.env_steps, "episodes": c.episodes, "updates": c.updates,
        "wall_s": round(c.wall_s, 1), "env_s": round(c.env_s, 1), "update_s": round(c.update_s, 1),
        "env_steps_per_s": round(c.env_steps / c.env_s, 1) if c.env_s else None,
        "updates_per_s": round(c.updates / c.update_s, 1) if c.update_s else None,
        "best_eval": best, "last_eval": c.rows[-1] if c.rows else {},
        "seed": cfg.seed, "git": git_hash(),
    }
    write_atomic(run_dir / "summary.json", json.dumps(finite_or_none(summary), indent=2, sort_keys=True) + "\n")


def finite_or_none(obj):
    """JSON-safe copy: NaN and infinities become None (null)."""
    if isinstance(obj, dict):
        return {k: finite_or_none(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [finite_or_none(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj
