"""``python -m export``: policy artifact -> int8 Kilobot firmware (C), with budget and error report.

Export (the default command)::

    python -m export --out kilobot_policy.c [--policy PATH | --onnx PATH [--world-json FILE]]
                     [--robots-calib 4 16] [--calib-episodes 1] [--calib-steps N] [--seed 0]
                     [--target-uids 0,5] [--verify host|avr] [--kilolib DIR]

loads the policy (default: the shipped placeholder ``export/data/default_policy.npz``), checks the
analytic flash/SRAM budget (refusing an architecture that does not fit, and saying what would),
calibrates on simulator rollouts of the policy itself, quantises, prints the error report and the
budget, renders the firmware and writes ``<out>``, ``kilobot_target.c`` beside it and
``<out>.manifest.json``, all-or-nothing.

Will it fit, before training::

    python -m export budget --history 20 --hidden 64 32 [--preset kilobot]
    python -m export budget --gru 32 [--preset kilobot]

Float actor vs int8 firmware in the simulator (firmware in the loop, :mod:`export.verify_cli`)::

    python -m export verify --closed-loop [--policy PATH] [--robots 16 32] [--episodes 200] [--out DIR]

Exit status: 0 done / fits; 1 does not fit (or verification failed); 2 bad input (a missing or
corrupt policy, an unwritable output path, ...). Errors are one line on stderr, never a traceback.
"""
from __future__ import annotations

import argparse
import inspect
import sys
from contextlib import ExitStack
from importlib import resources
from pathlib import Path
from typing import Any, Sequence

from .errors import BudgetError, ExportError, OutputError, PolicyError, VerifyError

EXIT_OK = 0
EXIT_DOES_NOT_FIT = 1
EXIT_USER_ERROR = 2
TARGET_FILE = "kilobot_target.c"  #: the beacon-only program, written beside --out
POLICY_FILE = "kilobot_policy.c"  #: the name render_firmware gives the policy program


class _Parser(argparse.ArgumentParser):
    """argparse that raises instead of exiting, so main() keeps the one-line error contract."""

    def error(self, message: str) -> None:  # type: ignore[override]
        raise ExportError(f"{self.prog}: {message} (see --help)")


def _uids(text: str) -> tuple[int, ...]:
    try:
        uids = tuple(int(t) for t in text.split(",") if t.strip() != "")
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got '{text}'") from None
    if not uids or any(not 0 <= u <= 0xFFFF for u in uids):
        raise argparse.ArgumentTypeError(f"target uids must be uint16 values, got '{text}'")
    return uids


def _positive(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got '{text}'") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {v}")
    return v


def export_parser() -> argparse.ArgumentParser:
    ap = _Parser(prog="python -m export",
                 description="Quantise a policy to int8 and render the Kilobot firmware "
                             "(sub-command 'budget': will an architecture fit?; 'verify --closed-loop': "
                             "float actor vs int8 firmware in the simulator).")
    ap.add_argument("--out", type=Path, default=Path(POLICY_FILE),
                    help=f"C file to write (default {POLICY_FILE}); {TARGET_FILE} and <out>.manifest.json go beside it")
    src = ap.add_mutually_exclusive_group()
    src.add_argument("--policy", type=Path, help="policy artifact .npz (default: the shipped reference policy, MAGDDPG-trained on the kilobot world)")
    src.add_argument("--onnx", type=Path, help="an ONNX MLP actor instead of a .npz policy")
    ap.add_argument("--world-json", type=Path, help="with --onnx: JSON file with 'world' and 't_prev'")
    ap.add_argument("--robots-calib", type=_positive, nargs="+", default=[4, 16], metavar="N",
                    help="robot counts of the calibration rollouts (default 4 16)")
    ap.add_argument("--calib-episodes", type=_positive, default=1, help="episodes per robot count (default 1)")
    ap.add_argument("--calib-steps", type=_positive, default=None,
                    help="control periods per calibration episode (default: the world's episode length)")
    ap.add_argument("--seed", type=int, default=0, help="calibration seed (default 0)")
    ap.add_argument("--percentile", type=float, default=100.0,
                    help="range percentile for exponent choice (default 100: the largest value seen)")
    ap.add_argument("--target-uids", type=_uids, default=None, metavar="UIDS",
                    help="comma-separated kilo_uids that run as the target beacon (default: the world's target_uid)")
    ap.add_argument("--kilolib", type=Path, default=None, metavar="DIR",
                    help="a built kilolib checkout: also write .elf/.hex images for KiloGUI beside the C files")
    ap.add_argument("--no-avr", action="store_true",
                    help="skip the exact avr-gcc budget even when the AVR toolchain is installed")
    ap.add_argument("--verify", choices=["host", "avr"], default=None,
                    help="host: build the C with the host compiler and check it against the emulator before writing")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    return ap


def budget_parser() -> argparse.ArgumentParser:
    from .numfmt import ACTIVATIONS
    ap = _Parser(prog="python -m export budget",
                 description="Will an actor with this history and these hidden layers (or a GRU actor of "
                             "--gru units) fit on a Kilobot? Exit 0 fits, 1 does not.")
    ap.add_argument("--history", type=_positive, default=None,
                    help="t_prev: history length in control periods (MLP actor; required without --gru)")
    ap.add_argument("--gru", type=_positive, default=None, metavar="H",
                    help="a recurrent actor instead: one GRU layer of H units (learn train-recurrent)")
    ap.add_argument("--hidden", type=_positive, nargs="*", default=[], metavar="W", help="hidden layer widths")
    ap.add_argument("--preset", default="kilobot", help="world preset (default kilobot)")
    ap.add_argument("--activation", default="elu", choices=[a for a in ACTIVATIONS if a != "identity"] + ["identity"],
                    help="hidden activation (default elu; elu/tanh/sigmoid cost a 256 B table per layer)")
    return ap


# --------------------------------------------------------------------------------------------
def _err(msg: str) -> None:
    print(f"error: {msg}", file=sys.stderr)


def run_budget(argv: Sequence[str]) -> int:
    from sim.config import preset

    from . import budget as bud
    args = budget_parser().parse_args(list(argv))
    try:
        world = preset(args.preset)
    except ValueError as e:
        raise ExportError(str(e)) from None
    if args.gru is not None:
        if args.history is not None or args.hidden:
            raise ExportError("--gru sizes a recurrent actor: leave out --history and --hidden")
        b = bud.estimate_gru(world, args.gru)
    elif args.history is None:
        raise ExportError("give --history T_PREV (MLP actor) or --gru H (recurrent actor)")
    else:
        b = bud.estimate(world, args.history, args.hidden, [args.activation] * len(args.hidden))
    print(b.table())
    if b.ok:
        return EXIT_OK
    print("would fit: " + "; ".join(b.suggest()))
    return EXIT_DOES_NOT_FIT


def _load(args: argparse.Namespace, stack: ExitStack):
    from .artifact import load_policy
    if args.onnx is not None:
        try:
            from .onnx_import import load_onnx_policy
        except ImportError as e:
            raise PolicyError(f"--onnx needs export.onnx_import and the 'onnx' package ({e})") from None
        return load_onnx_policy(args.onnx, world_json=args.world_json)
    if args.world_json is not None:
        raise ExportError("--world-json only goes with --onnx")
    if args.policy is not None:
        return load_policy(args.policy)
    ref = resources.files("export").joinpath("data", "default_policy.npz")
    return load_policy(stack.enter_context(resources.as_file(ref)))


def _render(qp: Any, target_uids: tuple[int, ...], extra: dict[str, Any]) -> dict[str, str]:
    try:
        from .render import render_firmware
    except ImportError as e:
        raise ExportError(f"the firmware renderer export.render is not available ({e})") from None
    params = inspect.signature(render_firmware).parameters
    kwargs = {k: v for k, v in extra.items() if k in params}
    files = render_firmware(qp, target_uids=target_uids, **kwargs)
    missing = {POLICY_FILE, TARGET_FILE} - set(files)
    assert not missing, f"render_firmware returned {sorted(files)}, lacks {sorted(missing)}"
    return files


def _verify_host(qp: Any, files: dict[str, str]) -> str:
    """Build the rendered C on the host and compare with the emulator (export.render.verify_host)."""
    try:
        from .render import verify_host
        result = verify_host(qp, files)
    except ImportError as e:
        raise ExportError(f"--verify host is not available in this installation ({e})") from None
    if not bool(getattr(result, "ok", result)):
        raise VerifyError(f"host verification failed: {result}")
    return f"host verification: {result}"


def _exact_budget(budget: Any, qp: Any, files: dict[str, str], *, skip: bool) -> Any:
    """Merge the exact avr-gcc figures (and the simavr-measured stack) into the budget, when possible."""
    from . import avr
    why = "--no-avr" if skip else avr.missing_tools()
    if why is not None:
        print(f"exact AVR budget skipped: {why}; the figures below are analytic estimates")
        return budget
    budget = budget.with_exact(avr.exact_budget(files, qp))
    if not budget.ok:
        print(budget.table())
        raise BudgetError(f"the avr-gcc build does not fit ({budget.summary()}); would fit: "
                          + "; ".join(budget.suggest()))
    return budget


def _verify_avr(qp: Any, files: dict[str, str]) -> str:
    """Run the AVR build in simavr and compare every output byte with the emulator (rung 3)."""
    from . import avr
    why = avr.missing_tools(simulate=True)
    if why:
        raise ExportError(f"--verify avr needs avr-gcc and simavr: {why}")
    check = avr.verify_simavr(qp, files)
    if not check.ok:
        raise VerifyError(f"AVR verification failed: {check}")
    return str(check)


def run_export(argv: Sequence[str]) -> int:
    args = export_parser().parse_args(list(argv))
    from . import budget as bud
    from .atomic import check_writable, write_files_atomic
    from .manifest import build_manifest, generator_version, manifest_json
    from .quantize import calibrate, error_report, quantize_policy

    out: Path = args.out
    if out.name in ("", ".", "..") or out.suffix != ".c":
        raise OutputError(f"--out must name a .c file, got '{out}'")
    target_path = out.with_name(TARGET_FILE)
    if target_path == out:
        raise OutputError(f"--out must not be named {TARGET_FILE} (that name is the beacon program's)")
    manifest_path = out.with_name(out.name + ".manifest.json")
    check_writable([out, target_path, manifest_path])  # fail before the slow part

    with ExitStack() as stack:
        policy = _load(args, stack)
    print(f"policy {policy.hash[:16]}: world '{policy.world.name}', t_prev {policy.t_prev}, "
          f"layers {' -> '.join(map(str, policy.layer_sizes))} ({', '.join(policy.activations)})")
    notes = policy.provenance.get("notes")
    if notes:
        print(f"  provenance: {notes}")

    budget = bud.for_policy(policy)
    if not budget.ok:
        print(budget.table())
        raise BudgetError(f"policy does not fit on the Kilobot ({budget.summary()}); would fit: "
                          + "; ".join(budget.suggest()))

    calib = calibrate(policy, episodes=args.calib_episodes, n_robots=args.robots_calib, seed=args.seed,
                      steps=args.calib_steps, progress=not args.no_progress and sys.stderr.isatty())
    qp = quantize_policy(policy, calib, percentile=args.percentile)
    report = error_report(policy, qp, calib)
    print(report.table())
    budget = bud.for_quantized(qp)
    if not budget.ok:  # pragma: no cover - same architecture as checked above
        print(budget.table())
        raise BudgetError(f"quantised policy does not fit ({budget.summary()})")

    target_uids = args.target_uids if args.target_uids is not None else (policy.world.target_uid,)
    files = _render(qp, target_uids, {"generator_version": generator_version(), "budget": budget,
                                      "error_report": report})
    budget = _exact_budget(budget, qp, files, skip=args.no_avr)
    print(budget.table())
    if args.verify == "host":
        print(_verify_host(qp, files))
    elif args.verify == "avr":
        print(_verify_avr(qp, files))
    options = {"target_uids": list(target_uids), "robots_calib": list(args.robots_calib),
               "calib_episodes": args.calib_episodes, "calib_steps": calib.info.get("steps"),
               "seed": args.seed, "percentile": args.percentile, "verify": args.verify,
               "source": str(args.onnx or args.policy or "default reference policy")}
    contents = {out: files[POLICY_FILE], target_path: files[TARGET_FILE]}
    if args.kilolib is not None:
        from . import avr
        images = avr.robot_images(files, args.kilolib)  # {"kilobot_policy.hex": bytes, ...}
        stems = {Path(POLICY_FILE).stem: out, Path(TARGET_FILE).stem: target_path}
        for name, data in images.items():
            contents[stems[Path(name).stem].with_suffix(Path(name).suffix)] = data
    manifest = build_manifest(policy, qp, budget, report, calib,
                              {out.name: files[POLICY_FILE], TARGET_FILE: files[TARGET_FILE]}, options)
    contents[manifest_path] = manifest_json(manifest)
    write_files_atomic(contents)
    print(f"wrote {out}, {target_path}, {manifest_path}")
    return EXIT_OK


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m export`` / ``kiloforge-export``; returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        if argv and argv[0] == "budget":
            return run_budget(argv[1:])
        if argv and argv[0] == "verify":
            from .verify_cli import run_verify
            return run_verify(argv[1:])
        return run_export(argv)
    except (BudgetError, VerifyError) as e:
        _err(str(e))
        return EXIT_DOES_NOT_FIT
    except ExportError as e:
        _err(str(e))
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        _err("interrupted; nothing written")
        return 130
