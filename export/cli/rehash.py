"""``python -m export rehash FILE [--out NEW]``: give a policy file one trusts the hash of its contents.

Loading a policy checks its ``policy_hash`` (the sha256 of its arrays and meta) and refuses a file
without one, or whose contents no longer match it. A file from an older tool, or edited on purpose,
can be re-hashed here: every other check of loading still applies, and the new file is written
atomically (in place unless ``--out`` is given; through a symbolic link, which stays:
:func:`kiloforge.io.through_links`).
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Sequence

from kiloforge.errors import printable
from kiloforge.policies import rehash_policy

from .common import EXIT_OK, Parser


def rehash_parser() -> argparse.ArgumentParser:
    ap = Parser(prog="python -m export rehash",
                description="Write a policy file one trusts with the hash of its contents (atomically).")
    ap.add_argument("policy", type=Path, help="the policy file (.npz)")
    ap.add_argument("--out", type=Path, default=None, help="write the re-hashed file here (default: replace FILE)")
    return ap


def run_rehash(argv: Sequence[str]) -> int:
    args = rehash_parser().parse_args(list(argv))
    policy, old = rehash_policy(args.policy, args.out)
    was = "had none" if old is None else ("unchanged" if old == policy.hash else f"was {old[:16]}...")
    print(f"wrote {printable(args.out or args.policy)}: policy_hash {policy.hash} ({was})")
    return EXIT_OK
