"""Write the packing-ceiling table of the kilobot world (sim/data/packing_ceiling.npz) and print it.

    python -m tools.packing_table                 # the shipped table (about 10 min on one core)
    python -m tools.packing_table --out /tmp/t.npz --radius 16.5 --comm 85 --arena 250

For every (dx, dy) wall distance on the grid, :func:`sim.tasks.ceiling.pack` searches a packing of discs
within range of the beacon; the table holds the counts and the configurations (see sim/tasks/ceiling.py).
Prints the envelope, the open-field capacity and the mean capacity over the env's beacon spawn.
"""
from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from kiloforge.io import write_atomic
from sim.tasks import ceiling
from sim.config import KILOBOT


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=ceiling.TABLE_PATH)
    ap.add_argument("--radius", type=float, default=KILOBOT.robot_radius_mm)
    ap.add_argument("--comm", type=float, default=KILOBOT.comm_radius_mm)
    ap.add_argument("--arena", type=float, default=KILOBOT.arena_half_mm)
    ap.add_argument("--step", type=float, default=ceiling.GRID_STEP_MM)
    args = ap.parse_args()
    world = dataclasses.replace(KILOBOT, robot_radius_mm=args.radius, comm_radius_mm=args.comm,
                                arena_half_mm=args.arena)
    prob = ceiling.Packing.of(world)
    t0 = time.time()

    def progress(i: int, j: int, k: int) -> None:
        print(f"  dx={prob.grid(args.step)[i]:5.1f} dy={prob.grid(args.step)[j]:5.1f}: {k:3d}  "
              f"({time.time() - t0:.0f} s)", flush=True)

    table = ceiling.build_table(prob, args.step, progress=progress)
    import io
    buf = io.BytesIO()
    np.savez_compressed(buf, **table)
    write_atomic(args.out, buf.getvalue())
    ceiling.load_table.cache_clear()
    t = ceiling.load_table(args.out)
    g = t.grid_mm
    print(f"\nenvelope (rows dx, columns dy, mm), {time.time() - t0:.0f} s:")
    print("      " + " ".join(f"{v:3.0f}" for v in g))
    for i, v in enumerate(g):
        print(f"{v:5.0f} " + " ".join(f"{c:3d}" for c in t.envelope[i]))
    raw_dips = int(np.sum(t.envelope != t.counts))
    w = ceiling.spawn_weights(world, g)
    print(f"open field: {t.envelope[-1, -1]}; mean over the beacon spawn: {float(w @ t.envelope @ w):.2f}; "
          f"grid points where the envelope exceeds the search: {raw_dips}")
    for M in (4, 16, 32):
        print(f"mean ceiling at {M} robots: {float(w @ np.minimum(t.envelope, M) @ w) / M:.3f}")


if __name__ == "__main__":
    main()
