"""What the exporter's sub-commands share: exit codes, the one-line-error parser, argument types,
policy loading."""
from __future__ import annotations

import argparse
from contextlib import ExitStack
from importlib import resources
from pathlib import Path

from kiloforge.actors.base import FloatPolicy
from kiloforge.policies import load_policy

from ..errors import ExportError
from ..interop.onnx_import import load_onnx_policy

EXIT_OK = 0
EXIT_FAIL = 1  #: does not fit, or a verification failed
EXIT_USER_ERROR = 2
DEFAULT_POLICY = ("data", "default_policy.npz")  #: the shipped reference policy, inside the export package


class Parser(argparse.ArgumentParser):
    """argparse that raises instead of exiting, so main() keeps the one-line error contract."""

    def error(self, message: str) -> None:  # type: ignore[override]
        raise ExportError(f"{self.prog}: {message} (see --help)")


def positive(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got '{text}'") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {v}")
    return v


def load(policy: Path | None, onnx: Path | None = None, world_json: Path | None = None) -> FloatPolicy:
    """The policy of ``--policy``, ``--onnx`` (with ``--world-json``), or the shipped default policy."""
    if onnx is not None:
        return load_onnx_policy(onnx, world_json=world_json)
    if world_json is not None:
        raise ExportError("--world-json only goes with --onnx")
    if policy is not None:
        return load_policy(policy)
    ref = resources.files("export").joinpath(*DEFAULT_POLICY)
    with ExitStack() as stack:
        return load_policy(stack.enter_context(resources.as_file(ref)))


def describe(policy: FloatPolicy) -> str:
    """The lines every sub-command prints about the policy it works on."""
    lines = [f"policy {policy.hash[:16]}: world '{policy.world.name}', {policy.describe()}"]
    notes = policy.provenance.get("notes")
    if notes:
        lines.append(f"  provenance: {notes}")
    return "\n".join(lines)
