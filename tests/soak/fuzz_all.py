"""The whole fuzzing run: >= 10,000 generated bad inputs over policy files, world JSON, ONNX graphs and the
command lines, with the property of tests/fuzz_targets.py; prints how each target's inputs ended.

    nice -n 15 python -m tests.soak.fuzz_all [--scale 1.0] [--only policy_bytes,onnx]

Exit status 0 when tracebacks, partial outputs, accepted corrupt files and unclean messages are all 0.
The test suite runs a slice of the same targets (tests/test_fuzz.py).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
import warnings
from pathlib import Path

from hypothesis import given

from tests import fuzz_targets as ft

#: inputs per target at --scale 1 (10,600 in all)
COUNTS = {"policy_bytes": 2500, "policy_meta": 2500, "policy_arrays": 1500, "world_json": 2000, "onnx": 1200,
          "cli_export": 700, "cli_sim": 200}


def run_target(name: str, n: int, root: Path, fx: ft.Fixtures, tally: ft.Tally) -> None:
    """``n`` generated inputs of one target, every outcome counted (nothing stops the run)."""
    work = root / name
    work.mkdir()
    strategy, check = {
        "policy_bytes": (ft.policy_byte_mutation(), lambda c: ft.check_policy_file(c[0], work, c[1])),
        "policy_meta": (ft.policy_meta_mutation(), lambda c: ft.check_policy_file(c[0], work, c[1])),
        "policy_arrays": (ft.policy_array_mutation(), lambda c: ft.check_policy_file(c[0], work, c[1])),
        "world_json": (ft.world_json_text(), lambda text: ft.check_world_json(text, work, fx.onnx_bare)),
        "onnx": (ft.onnx_mutation(), lambda data: ft.check_onnx(data, work)),
        "cli_export": (ft.st.data(), lambda data: ft.cli_case("export", data, fx, work / "out")),
        "cli_sim": (ft.st.data(), lambda data: ft.cli_case("sim", data, fx, work / "out")),
    }[name]

    @ft.fuzz_settings(n)
    @given(case=strategy)
    def t(case):
        tally.add(name, *check(case))
    t()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", type=float, default=1.0, help="multiply every target's input count")
    ap.add_argument("--only", default=None, help="comma-separated targets (default all): " + ", ".join(COUNTS))
    args = ap.parse_args()
    names = args.only.split(",") if args.only else list(COUNTS)
    tally = ft.Tally()
    times = {}
    warnings.simplefilter("ignore")
    with tempfile.TemporaryDirectory(prefix="kf-fuzz-all-") as d:
        root = Path(d)
        fx = ft.Fixtures(root / "fixtures")
        for name in names:
            t0 = time.perf_counter()
            run_target(name, max(1, round(COUNTS[name] * args.scale)), root, fx, tally)
            times[name] = time.perf_counter() - t0
            c = tally.counts.get(name, {})
            print(f"{name}: {sum(c.values())} inputs in {times[name]:.0f} s", flush=True)
    cols = ft.OUTCOMES
    print()
    print(f"| target | inputs | {' | '.join(cols)} | s |")
    print("|---|" + "---:|" * (len(cols) + 2))
    total = {o: 0 for o in cols}
    for name in names:
        c = tally.counts.get(name, {o: 0 for o in cols})
        for o in cols:
            total[o] += c[o]
        print(f"| {name} | {sum(c.values())} | {' | '.join(str(c[o]) for o in cols)} | {times[name]:.0f} |")
    print(f"| **all** | **{sum(total.values())}** | {' | '.join(f'**{total[o]}**' for o in cols)} | "
          f"{sum(times.values()):.0f} |")
    bad = sum(total[o] for o in ft.FAILURES)
    for f in tally.failures:
        print("\n" + f)
    print(f"\nfailures (tracebacks + partial outputs + accepted corrupt + unclean messages): {bad}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
