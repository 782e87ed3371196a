"""Phototaxis firmware in Kilombo under a lamp (its lighting callback reads sim/light.py's field) vs our simulator.

    python -m tests.bench.bench_kilombo_phototaxis --kilombo-dir DIR [--policy stop_in_light run_and_tumble default ...]
        [--robots 16] [--episodes 40] [--steps 300] [--seed 0] [--no-sensor-model] [--json FILE]

Not a test: it prints a table (docs/results/phototaxis.md has the measured one; docs/kilombo.md how to build
Kilombo). ``DIR`` is a Kilombo install prefix (``KILOMBO_DIR`` when the option is not given; without either, a
one-line error, exit 2). Per policy (a file or a shipped phototaxis policy: ``stop_in_light``, ``run_and_tumble``,
``default``):

1. Quantises it as ``python -m export --task phototaxis`` does, renders the firmware and builds it unchanged for
   Kilombo (``-DKILOMBO``) with ``tests/bench/kilombo/kilombo_adapter.c``, whose lighting callback gives
   ``get_ambientlight()`` the reading of our phototaxis world: the floor light plus the spot lamp's field at the
   robot's centre (sim/light.py), times the robot's sensor gain, plus its offset and per-reading noise, rounded and
   clipped to 0..1023. Gains and offsets are drawn per episode as SwarmEnv draws them (:func:`sim.light.draw_sensors`,
   own seeds); ``--no-sensor-model`` gives the bare field instead. Kilombo never returns -1 (our world: 2 % dropout).
2. Runs M robots (the program sees uids 1..M, as in our closed loop; no beacon) from exactly the start states of ``python -m export
   verify --task phototaxis --robots M --episodes E --steps T --seed S``, mirrored into Kilombo's frame
   (bench_kilombo.py), for ``(T + 1) * 31`` ticks, and counts after each control step the robots whose centre is
   within the spot's nominal radius; final = the mean over the last quarter (the task's metric).
3. Runs our closed loop (int8 firmware emulator) and the float policy on the same episodes.

Each row: final fraction in the spot (mean ± 95 % CI) and its ratio to our closed loop (paired bootstrap CI).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from export.errors import ExportError
from kiloforge.errors import KiloforgeError
from sim.config import WorldConfig
from sim.light import draw_sensors
from sim.metrics import final_success, summarise
from sim.tasks.phototaxis import spot_of
from tests.bench.bench_kilombo import (_die, _fmt_ratio, _kilombo_prefix, build, kilombo_bots, kilombo_lamps,
                                       kilombo_params, log_positions, run_episode)

TASK = "phototaxis"


def starts(cfg: WorldConfig, n_robots: int, episodes: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(positions (M, 2), headings (M,)) of each episode of ``export verify``'s closed loop (same env seeds, batching)."""
    from export.verify.closed_loop import batch_env_seeds, default_n_envs
    from sim.env import SwarmEnv

    B = default_n_envs(episodes, n_robots)
    out = []
    env = SwarmEnv(cfg, B, n_robots, seed=0, task=TASK)
    for s in batch_env_seeds(seed, math.ceil(episodes / B)):
        env.reset(seed=s)
        out += [(env.pos[e].copy(), env.heading[e].copy()) for e in range(B)]
    return out[:episodes]


def in_spot_curve(xy: np.ndarray, cfg: WorldConfig) -> np.ndarray:
    """(steps + 1, M, 2) positions in our frame -> the fraction of robots in the spot after each step (steps,).

    >>> from sim.config import preset
    >>> cfg = dataclasses.replace(preset("kilobot"), lamps="spot:0,0,100,40,600")
    >>> in_spot_curve(np.array([[[0, 0], [0, 0]], [[50, 0], [0, 101]]], float), cfg).tolist()
    [0.5]
    """
    spot = spot_of(cfg)
    d = np.hypot(xy[1:, :, 0] - spot.x, xy[1:, :, 1] - spot.y)
    return (d <= spot.radius).mean(axis=1)


def run_kilombo(binary: Path, cfg: WorldConfig, eps: list, steps: int, seed: int, sensor_model: bool) -> np.ndarray:
    """Final fraction in the spot of every episode in Kilombo (one process each, in a scratch directory)."""
    finals = []
    with tempfile.TemporaryDirectory(prefix="kilombo_photo_") as tmp:
        work = Path(tmp)
        for e, (pos, heading) in enumerate(eps):
            M = pos.shape[0]
            params = kilombo_params(cfg, steps, seed * 100_000 + e)
            params["kfUidOffset"] = 1  # the program sees uid i + 1 (kilombo_bots)
            if sensor_model:
                s = draw_sensors(cfg, M, [np.random.default_rng(np.random.SeedSequence([seed, e]))])
                gain, offset = (None, None) if s is None else (s.gain[0], s.offset[0])
                params.update(kilombo_lamps(cfg, gain, offset))  # index: Kilombo's ID, robot i
            else:
                params.update(kilombo_lamps(dataclasses.replace(cfg, light_noise=0.0)))
            run_episode(binary, work, params, kilombo_bots(None, pos, heading), f"episode {e}")
            xy = log_positions((work / "log.txt").read_text(), M, cfg.period_ticks, steps)
            finals.append(final_success(in_spot_curve(xy, cfg)[None])[0])
    return np.array(finals)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kilombo-dir", default=None, help="Kilombo install prefix (default: $KILOMBO_DIR)")
    ap.add_argument("--policy", nargs="+", default=["stop_in_light", "run_and_tumble", "default"],
                    help="policy files or shipped phototaxis policies (default: the two baselines and the learned "
                         "default)")
    ap.add_argument("--robots", type=int, default=16, help="robots (default 16)")
    ap.add_argument("--episodes", type=int, default=40, help="episodes (default 40)")
    ap.add_argument("--steps", type=int, default=300, help="control periods per episode (default 300)")
    ap.add_argument("--seed", type=int, default=0, help="episode seed, as export verify (default 0)")
    ap.add_argument("--no-sensor-model", action="store_true",
                    help="Kilombo reads the bare light field (no per-robot gain, offset or noise)")
    ap.add_argument("--json", type=Path, default=None, help="write every per-episode number here")
    args = ap.parse_args(argv)
    try:
        prefix = _kilombo_prefix(args.kilombo_dir)
        if args.robots < 1 or args.episodes < 1 or args.steps < 1:
            raise ExportError("--robots, --episodes and --steps must be >= 1")
        return _bench(args, prefix)
    except KiloforgeError as e:
        _die(str(e))
    return 2


def _bench(args, prefix: Path) -> int:
    from export.codegen.render import POLICY_FILE, render_firmware
    from export.quantize import calibrate, quantize_policy
    from kiloforge.shipped import load_task_policy
    from export.verify.closed_loop import run_firmware, run_float

    M, E, T, seed = args.robots, args.episodes, args.steps, args.seed
    rows, doc = [], []
    print(f"phototaxis in Kilombo at {prefix}: {M} robots, {E} episodes x {T} steps, seed {seed}, "
          f"sensor model {'off' if args.no_sensor_model else 'on'}")
    for name in args.policy:
        policy = load_task_policy(name, TASK)
        qp = quantize_policy(policy, calibrate(policy, episodes=1, n_robots=(4, 16), seed=0, task=TASK))
        world = dataclasses.replace(qp.world, episode_steps=T)
        eps = starts(world, M, E, seed)
        t0 = time.perf_counter()
        with tempfile.TemporaryDirectory(prefix="kilombo_build_") as tmp:
            prog = Path(tmp) / "kilobot_policy.c"
            prog.write_text(render_firmware(qp)[POLICY_FILE])
            k = run_kilombo(build(prefix, [prog], Path(tmp) / "kf_policy"), world, eps, T, seed,
                            not args.no_sensor_model)
        wall = time.perf_counter() - t0
        ours = run_firmware(qp, M, E, seed, steps=T, task=TASK).metrics().per_episode("final_in_spot")
        flt = run_float(policy, M, E, seed, steps=T, task=TASK).metrics().per_episode("final_in_spot")
        rows.append((name, k, ours, flt, wall))
        print(f"  {name}: Kilombo {summarise(k)} ({wall:.0f} s), ours int8 {summarise(ours)}, float {summarise(flt)}",
              flush=True)
        doc.append({"policy": name, "policy_hash": policy.hash, "kilombo": k.tolist(), "ours_int8": ours.tolist(),
                    "ours_float": flt.tolist()})
    print()
    head = ("policy", "Kilombo (int8 firmware)", "ours: closed loop (int8)", "ours: float", "Kilombo / ours [95% CI]")
    print(" | ".join(head))
    for name, k, ours, flt, _ in rows:
        print(" | ".join((name, str(summarise(k)), str(summarise(ours)), str(summarise(flt)),
                          _fmt_ratio(k, ours, True, seed))))
    if args.json is not None:
        from kiloforge.io import write_atomic

        write_atomic(args.json, json.dumps({"robots": M, "episodes": E, "steps": T, "seed": seed,
                                            "sensor_model": not args.no_sensor_model, "kilombo": str(prefix),
                                            "rows": doc}, indent=1))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
