"""Make an untrained placeholder policy (the architecture of the shipped default policy).

``export/data/default_policy.npz`` is now a *trained* reference policy (see ``docs/report.md`` and
``tests/bench/reproduce_thesis.py``); before it existed, ``python -m export`` exported this
placeholder so that the whole pipeline ran out of the box. The placeholder stays useful as a
deterministic, training-free policy of the same shape. It is **untrained**: a
seeded random initialisation per thesis §4.3.1 (hidden layers U[-1/sqrt(f), 1/sqrt(f)] with f the
layer's input width, output layer U[-3e-3, 3e-3]), so its robots barely move.

Its architecture: hidden sizes (32, 32) ELU in the ``kilobot`` world and the largest history
(at most :data:`MAX_T_PREV`) that the analytic budget (:mod:`export.budget`) accepts with at least
:data:`FLASH_HEADROOM_B` of flash to spare (room for error in the code-size estimate).

Make it with ``python -m export.make_placeholder --out P.npz`` (deterministic: same seed, same
bytes); the default output is ``placeholder_policy.npz`` in the current directory, never the shipped
default policy.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

import numpy as np

from sim.config import WorldConfig, preset

from .artifact import Policy, save_policy

SEED = 20240601  #: fixed seed of the placeholder
HIDDEN = (32, 32)
ACTIVATION = "elu"
MAX_T_PREV = 20  #: the thesis studies histories of 1..10 periods; 20 is ample for a placeholder
FLASH_HEADROOM_B = 1_500  #: flash left free for error in the code estimate
OUT = Path("placeholder_policy.npz")  #: default output (the shipped default policy is trained; see the module doc)
NOTE = "placeholder: untrained random initialisation; replace with a trained policy"


def init_policy(world: WorldConfig, t_prev: int, hidden: Sequence[int], activation: str = "elu",
                seed: int = 0, out_scale: float = 3e-3, provenance: dict | None = None) -> Policy:
    """A randomly initialised MLP actor (thesis §4.3.1): U[±1/sqrt(f)] hidden, U[±out_scale] output."""
    rng = np.random.default_rng(np.random.SeedSequence(seed))
    sizes = [world.history_dim(t_prev), *hidden, 2]
    ws, bs = [], []
    for k in range(len(sizes) - 1):
        f = sizes[k]
        lim = out_scale if k == len(sizes) - 2 else 1.0 / np.sqrt(f)
        ws.append(rng.uniform(-lim, lim, size=(sizes[k + 1], f)).astype(np.float32))
        bs.append(rng.uniform(-lim, lim, size=(sizes[k + 1],)).astype(np.float32))
    acts = [activation] * len(hidden) + ["identity"]
    return Policy(weights=ws, biases=bs, activations=acts, t_prev=t_prev, world=world,
                  provenance=dict(provenance or {}))


def largest_fitting_t_prev(world: WorldConfig, hidden: Sequence[int], cap: int = MAX_T_PREV,
                           headroom: int = FLASH_HEADROOM_B) -> int:
    """Largest t_prev <= cap whose analytic budget fits with ``headroom`` bytes of flash to spare."""
    from .budget import estimate

    best = 0
    for t in range(1, cap + 1):
        b = estimate(world, t, hidden, [ACTIVATION] * len(hidden) + ["identity"])
        if b.ok and b.flash_total + headroom <= b.flash_limit:
            best = t
    if best == 0:
        raise SystemExit(f"no history length fits at hidden sizes {tuple(hidden)}")
    return best


def make_placeholder(out: Path = OUT) -> Policy:
    world = preset("kilobot")
    t_prev = largest_fitting_t_prev(world, HIDDEN)
    prov = {"trainer": "none", "seed": SEED, "date": None, "git": None, "notes": NOTE,
            "init": "thesis §4.3.1: hidden U[-1/sqrt(f), 1/sqrt(f)], output U[-3e-3, 3e-3]",
            "script": "python -m export.make_placeholder"}
    policy = init_policy(world, t_prev, HIDDEN, ACTIVATION, seed=SEED, provenance=prov)
    save_policy(policy, out)
    return policy


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m export.make_placeholder", description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=OUT, help=f"output file (default: {OUT})")
    args = ap.parse_args(argv)
    p = make_placeholder(args.out)
    print(f"wrote {args.out} ({args.out.stat().st_size} B): t_prev={p.t_prev}, layers {p.layer_sizes}, "
          f"hash {p.hash[:16]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
