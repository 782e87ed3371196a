"""Several policies across the robustness suite in one run, side by side, on the same episodes.

    python -m tests.bench.robustness_compare export/data/default_policy.npz runs/esdr_s2 baseline \
        --robots 4 16 32 --episodes 30 --steps 300 --seed 20261202 --out runs/robust_cmp

Each entry is a run directory (its ``policy_best.npz``), a ``.npz`` artifact, or ``baseline`` (the
hand-written searcher). Every policy meets the same episode seeds in every variant of
:func:`sim.variants.robustness_suite` (kilobot world: the first policy's). Prints one markdown table
per robot count: final coverage per variant and policy, its percentage of that policy's nominal
coverage, and the worst variant of each; writes ``robustness_compare.json`` and ``.md`` to ``--out``.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from kiloforge.io import write_atomic
from kiloforge.policies import load_policy, policy_paths, swarm_policy
from sim.baselines import make_policy
from sim.config import HELD_OUT_SEED, preset
from sim.robustness import SuiteTable, run_suite
from sim.variants import robustness_suite


def factories(entries: list[str]):
    """(name → policy factory of a world, the world of the first artifact or the kilobot world)."""
    out, world = {}, None
    for name, path in policy_paths([e for e in entries if e != "baseline"]).items():
        pol = load_policy(path)
        world = world or pol.world
        out[name] = lambda w, pol=pol: swarm_policy(pol, w)
    if "baseline" in entries:
        out["hand-written"] = lambda w: make_policy("baseline", w)
    return out, world or preset("kilobot")


def pct(f: float | None) -> str:
    return "n/a" if f is None else f"{100 * f:.0f}"


def table_md(tables: dict[str, SuiteTable], M: int) -> str:
    names = list(tables)
    lines = ["| variant | " + " | ".join(f"{n} | %" for n in names) + " |", "|---|" + "---:|---:|" * len(names)]
    for v in next(iter(tables.values())).cells:
        cells = " | ".join(f"{t.cells[v][M].mean:.3f} | {pct(t.fraction(v, M))}" for t in tables.values())
        lines.append(f"| {v} | {cells} |")
    worst = " | ".join(f"{t.worst(M)[0]} | {pct(t.worst(M)[1])}" for t in tables.values())
    lines.append(f"| **worst** | {worst} |")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    ap.add_argument("policies", nargs="+", help="run directories, .npz files, or 'baseline'")
    ap.add_argument("--robots", nargs="+", type=int, default=[4, 16, 32])
    ap.add_argument("--episodes", type=int, default=30)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--seed", type=int, default=HELD_OUT_SEED, help="episode seed no training used")
    ap.add_argument("--variants", nargs="+", default=None, metavar="NAME",
                    help="only these variants of the suite (nominal is always run; default: all)")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    try:
        makers, world = factories(args.policies)
    except ValueError as e:  # a policy given twice
        ap.error(str(e))
    suite = robustness_suite(world)
    if args.variants:
        unknown = [v for v in args.variants if v not in suite]
        if unknown:
            raise SystemExit(f"error: unknown variant '{unknown[0]}'; the suite has: {', '.join(suite)}")
        suite = {k: v for k, v in suite.items() if k == "nominal" or k in args.variants}
    tables = {}
    for name, make in makers.items():
        print(f"running {name} ...", flush=True)
        tables[name] = run_suite(make, world, args.robots, args.episodes, args.steps, args.seed, suite=suite,
                                 progress=True)
    md = [f"# Robustness suite: {', '.join(tables)} ({world.name} world, {args.episodes} episodes x "
          f"{args.steps} steps, seed {args.seed})"]
    for M in args.robots:
        md += [f"\n## {M} robots: final coverage and % of the policy's nominal\n", table_md(tables, M)]
    text = "\n".join(md) + "\n"
    print(text)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / "robustness_compare.json",
                 json.dumps({n: t.to_dict() for n, t in tables.items()}, indent=1, sort_keys=True) + "\n")
    write_atomic(out / "robustness_compare.md", text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
