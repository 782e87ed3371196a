"""Make a trained policy the shipped default, with the evidence for choosing it in its provenance.

    python -m tools.ship_default runs/es_s2/policy_best.npz --evaluation runs/es_eval/seeds.json \
        --notes "..." [--out export/data/default_policy.npz]

Copies the policy (its arrays unchanged) and adds to its provenance: ``notes``, ``selection`` (the
per-seed held-out evaluation that chose it, from tests/bench/learning_seeds.py's ``seeds.json``) and
the shipping date. The file is written atomically and loads with the stored hash checked.
"""
from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

from kiloforge.policies import load_policy, save_policy


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    ap.add_argument("policy")
    ap.add_argument("--evaluation", required=True, help="seeds.json of tests/bench/learning_seeds.py")
    ap.add_argument("--notes", required=True)
    ap.add_argument("--out", default=str(ROOT / "export" / "data" / "default_policy.npz"))
    args = ap.parse_args()
    p = load_policy(args.policy)
    prov = {**p.provenance, "notes": args.notes, "selection": json.loads(Path(args.evaluation).read_text()),
            "shipped": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")}
    prov.setdefault("date", prov["shipped"])
    save_policy(dataclasses.replace(p, provenance=prov), args.out)
    q = load_policy(args.out)
    print(f"wrote {args.out} ({Path(args.out).stat().st_size} bytes, hash {q.hash})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
