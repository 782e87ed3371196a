"""``python -m export`` (the default command): policy artifact -> int8 Kilobot firmware (C).

    python -m export --out kilobot_policy.c [--policy PATH | --onnx PATH [--world-json FILE]]
                     [--robots-calib 4 16] [--calib-episodes 1] [--calib-steps N] [--seed 0]
                     [--target-uids 0,5] [--verify host|avr] [--kilolib DIR]

loads the policy (default: the shipped reference policy ``export/data/default_policy.npz``), checks
the analytic flash/SRAM budget (refusing an architecture that does not fit, and saying what would),
calibrates on simulator rollouts of the policy itself, quantises, prints the error report and the
budget, renders the firmware and writes ``<out>``, ``kilobot_target.c`` beside it and
``<out>.manifest.json``, all-or-nothing.
"""
from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path
from typing import Any, Sequence

from kiloforge.actors.base import QuantizedActor
from kiloforge.cliparse import program
from kiloforge.errors import OutputError, printable
from kiloforge.io import check_writable, write_files_atomic
from kiloforge.validate import parse_decimal, quote
from sim.config import KILOBOT, run_steps
from sim.tasks import Task, get_task
from sim.tasks.emitter import task_emitter

from ..codegen import budget as bud
from ..codegen.manifest import build_manifest, generator_version, manifest_json
from ..codegen.render import POLICY_FILE, EmitterFirmware, render_firmware
from ..errors import BudgetError, ExportError, VerifyError
from ..verify import avr
from ..verify.hostbuild import verify_host
from .common import (EXIT_OK, Parser, add_calibration, add_quiet, add_task, check_robots, describe, load, policy_help,
                     quantise)


def _uids(text: str) -> tuple[int, ...]:
    """``--target-uids``: comma-separated decimal uint16 values (ASCII digits only, :func:`parse_decimal`)."""
    try:
        uids = tuple(parse_decimal(t) for t in text.split(",") if t.strip() != "")
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated decimal integers (ASCII digits), "
                                         f"got {quote(text)}") from None
    if not uids or any(not 0 <= u <= 0xFFFF for u in uids):
        raise argparse.ArgumentTypeError(f"emitter uids must be uint16 values (0..65535), got {quote(text)}")
    return uids


def export_parser() -> argparse.ArgumentParser:
    ap = Parser(prog="python -m export",
                description="Quantise a policy to int8 and render the Kilobot firmware "
                            "(sub-command 'budget': will an architecture fit?; 'verify': "
                            "float actor vs int8 firmware in the simulator, closed loop).")
    ap.add_argument("--out", type=Path, default=Path(POLICY_FILE),
                    help=f"C file to write (default {POLICY_FILE}); <out>.manifest.json and, for a task with an emitter, "
                         f"the emitter's own program (e.g. kilobot_target.c) go beside it")
    src = ap.add_mutually_exclusive_group()
    src.add_argument("--policy", type=Path, help=policy_help())
    src.add_argument("--onnx", type=Path, help="an ONNX MLP actor instead of a .npz policy")
    add_task(ap)
    ap.add_argument("--world-json", type=Path, help="with --onnx: JSON file with 'world' and 't_prev'")
    add_calibration(ap)
    ap.add_argument("--target-uids", type=_uids, default=None, metavar="UIDS", dest="emitter_uids",
                    help="comma-separated kilo_uids that run the task's emitter role (default: the world's emitter uid)")
    ap.add_argument("--kilolib", type=Path, default=None, metavar="DIR",
                    help="a built kilolib checkout: also write .elf/.hex images for KiloGUI beside the C files")
    ap.add_argument("--no-avr", action="store_true",
                    help="skip the exact avr-gcc budget even when the AVR toolchain is installed")
    ap.add_argument("--verify", choices=["host", "avr"], default=None,
                    help="host: build the C with the host compiler and check it against the emulator before writing")
    add_quiet(ap)
    return ap


def _exact_budget(budget: bud.Budget, qp: QuantizedActor, files: dict[str, str], *, skip: bool) -> bud.Budget:
    """Merge the exact avr-gcc figures (and the simavr-measured stack) into the budget, when possible."""
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


def _kilolib_flash(budget: bud.Budget, sizes: dict[str, avr.Sizes]) -> bud.Budget:
    """The budget with each program's flash measured on its real kilolib build (the ELF's text + data, what
    KiloGUI uploads) in place of the stand-in estimate."""
    exact = {**(budget.exact or {}), "flash": sizes[POLICY_FILE].flash, "flash_source": "kilolib build"}
    exact.update({f"{Path(name).stem}_flash": s.flash for name, s in sizes.items() if name != POLICY_FILE})
    budget = budget.with_exact(exact)
    if not budget.ok:
        print(budget.table())
        raise BudgetError(f"the kilolib build does not fit ({budget.summary()}); would fit: " + "; ".join(budget.suggest()))
    return budget


def _verify_host(qp: QuantizedActor, files: dict[str, str], task: Task) -> str:
    """Build the rendered C on the host and compare with the emulator (rung 2)."""
    result = verify_host(qp, files, task=task)
    if not result.ok:
        raise VerifyError(f"host verification failed: {result}")
    return f"host verification: {result}"


def _verify_avr(qp: QuantizedActor, files: dict[str, str]) -> str:
    """Run the AVR build in simavr and compare every output byte with the emulator (rung 3)."""
    why = avr.missing_tools(simulate=True)
    if why:
        raise ExportError(f"--verify avr needs avr-gcc and simavr: {why}")
    check = avr.verify_simavr(qp, files)
    if not check.ok:
        raise VerifyError(f"AVR verification failed: {check}")
    return str(check)


def next_steps(argv: Sequence[str], out: Path, emitter_path: Path, emitter_uids: Sequence[int],
               kilolib: Path | None, role: str = "") -> list[str]:
    """The lines printed after a successful export: what to run next to get the policy onto robots (no emitter
    uids: a world without an emitter, one image for every robot; ``role``: what the task calls its emitter robot)."""
    if not emitter_uids:
        if kilolib is not None:
            return [f"next: flash {out.with_suffix('.hex')} onto every robot with KiloGUI",
                    "      before you flash (calibration, lighting, uids): docs/flashing.md"]
        return [f"next: .hex images for KiloGUI: {program('python -m export')} {shlex.join(argv)} --kilolib DIR "
                "(DIR: your built kilolib checkout)",
                "      then flash every robot with it: docs/flashing.md"]
    uids = f"kilo_uid {', '.join(map(str, emitter_uids))}"
    if kilolib is not None:
        return [f"next: flash {out.with_suffix('.hex')} onto every robot with KiloGUI; the robot with {uids} "
                f"is {role} ({emitter_path.with_suffix('.hex')}: its own image)",
                "      before you flash (calibration, lighting, uids): docs/flashing.md"]
    return [f"next: .hex images for KiloGUI: {program('python -m export')} {shlex.join(argv)} --kilolib DIR "
            "(DIR: your built kilolib checkout)",
            f"      then flash them (the robot with {uids} is {role}): docs/flashing.md"]


def run_export(argv: Sequence[str]) -> int:
    args = export_parser().parse_args(list(argv))
    out: Path = args.out
    if out.name in ("", ".", "..") or out.suffix != ".c":
        raise OutputError(f"--out must name a .c file, got '{out}'")
    args.task = get_task(args.task)  # resolved once: a task file is imported once, every later step gets this Task
    emitter = EmitterFirmware(args.task) if task_emitter(args.task) else None  # its program's file name, or none
    emitter_path = out.with_name(emitter.program) if emitter else None
    if emitter_path == out:
        raise OutputError(f"--out must not be named {emitter.program} (that name is the emitter program's)")
    manifest_path = out.with_name(out.name + ".manifest.json")
    programs = [out] + ([emitter_path] if emitter_path else [])
    image_paths = [p.with_suffix(x) for p in programs for x in (".hex", ".elf")] if args.kilolib else []
    check_writable([*programs, manifest_path, *image_paths])  # fail before the slow part
    if args.kilolib is not None:
        avr.find_kilolib(args.kilolib)  # a bad --kilolib (or no AVR toolchain) too

    policy = load(args.policy, args.onnx, args.world_json, args.task)
    has_emitter = policy.world.has_roles  # without one: no emitter role, no emitter program
    if not has_emitter and args.emitter_uids is not None:
        raise ExportError(f"--target-uids: the policy's world '{policy.world.name}' has no emitter "
                          f"(task {policy.task.name})")
    if policy.world.name != KILOBOT.name:
        print(f"warning: this policy was trained in the '{policy.world.name}' world, not the Kilobot's "
              f"('{KILOBOT.name}': 33 mm bodies, collisions, leg-pivot motion, the Kilobot radio); on robots it "
              f"will not do what the simulator showed: train with --world {KILOBOT.name}", file=sys.stderr)
    print(describe(policy))
    check_robots(policy.world, args.robots_calib, "--robots-calib", args.task)
    calib_steps = run_steps(policy.world, args.calib_steps, "--calib-steps")
    budget = bud.for_policy(policy)
    if not budget.ok:
        print(budget.table())
        raise BudgetError(f"policy does not fit on the Kilobot ({budget.summary()}); would fit: "
                          + "; ".join(budget.suggest()))

    progress = not args.quiet and sys.stderr.isatty()
    calib, qp, report = quantise(policy, args, args.seed, calib_steps, progress)
    print(report.table())
    budget = bud.for_quantized(qp)
    if not budget.ok:  # pragma: no cover - same architecture as checked above
        print(budget.table())
        raise BudgetError(f"quantised policy does not fit ({budget.summary()})")

    emitter_uids = (() if not has_emitter else args.emitter_uids if args.emitter_uids is not None
                    else (policy.world.emitter_uid,))
    files = render_firmware(qp, emitter_uids=emitter_uids or None, generator_version=generator_version(), task=args.task)
    budget = _exact_budget(budget, qp, files, skip=args.no_avr)
    built: dict[Path, bytes] = {}
    if args.kilolib is not None:
        images, sizes = avr.robot_images(files, args.kilolib)  # {"kilobot_policy.hex": bytes, ...}
        budget = _kilolib_flash(budget, sizes)
        stems = {Path(POLICY_FILE).stem: out, **({emitter.stem: emitter_path} if emitter and emitter_path else {})}
        built = {stems[Path(name).stem].with_suffix(Path(name).suffix): data for name, data in images.items()}
    print(budget.table())
    if args.verify == "host":
        print(_verify_host(qp, files, args.task))
    elif args.verify == "avr":
        print(_verify_avr(qp, files))
    options = {"emitter_uids": list(emitter_uids), "robots_calib": list(args.robots_calib),
               "calib_episodes": args.calib_episodes, "calib_steps": calib.info.get("steps"),
               "seed": args.seed, "percentile": args.percentile, "verify": args.verify,
               "source": str(args.onnx or args.policy or "default reference policy")}
    emitter_c = {emitter_path: files[emitter.program]} if emitter and emitter_path and has_emitter else {}
    contents: dict[Path, Any] = {out: files[POLICY_FILE], **emitter_c, **built}
    manifest = build_manifest(policy, qp, budget, report, calib, {p.name: data for p, data in contents.items()},
                              options)
    contents[manifest_path] = manifest_json(manifest)  # last: the set's record (kiloforge.io)
    write_files_atomic(contents)
    print(f"wrote {', '.join(map(printable, contents))}")
    if not args.quiet:
        print("\n".join(next_steps(argv, out, emitter_path or out, emitter_uids, args.kilolib,
                                    emitter.role_name if emitter else "")))
    return EXIT_OK
