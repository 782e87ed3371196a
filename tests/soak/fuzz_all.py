"""The whole fuzzing run: >= 10,000 generated bad inputs over policy files, world JSON, ONNX graphs and every
command line (export, budget, verify, rehash, sim, learn evaluate, learn plot, --version), with the property of
tests/fuzz_targets.py and tests/fuzz_commands.py; prints how each target's inputs ended.

    nice -n 15 python -m tests.soak.fuzz_all [--scale 1.0] [--only policy_bytes,onnx] [--jobs 2]

The targets of issue 47 (tests/fuzz_commands.py): ``names`` (mathtext, non-UTF-8, control characters and
too-long names as outputs, policy files, world names and labels of every command), ``run_folders``
(``learn plot`` of mutated config.json / metrics.csv, FIFOs, ``/dev/zero``), ``stdout`` (``/dev/full``, a
closed pipe, an ASCII-only stream), ``disk_full`` (RLIMIT_FSIZE while every command writes), ``weights``
(arrays scaled beyond the int8 format), ``part_a`` (searcher parameters, RBF constants, huge episode
lengths, a bad CC, Unicode target uids, ONNX external data).

Columns: ``traceback`` an exception left the command; ``hang`` an input still running after
``fuzz_commands.HANG_S``; ``partial_output`` files changed by a refusal, temporaries left, or a success
missing an output; ``accepted_corrupt`` a corrupt input accepted; ``bad_message`` a refusal that is not
exactly one clean stderr line (a NumPy warning beside it included). Exit status 0 when all of these are 0.
The test suite runs a slice of the same targets (tests/test_fuzz.py).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
import warnings
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from hypothesis import given

from tests import fuzz_commands as fc
from tests import fuzz_targets as ft

#: inputs per target at --scale 1 (14,150 in all)
COUNTS = {"policy_bytes": 2500, "policy_meta": 2500, "policy_arrays": 1500, "world_json": 2000, "onnx": 1200,
          "cli_export": 700, "cli_sim": 200,
          "names": 500, "run_folders": 1500, "stdout": 400, "disk_full": 250, "weights": 300, "part_a": 600}


def run_target(name: str, n: int, root: Path) -> tuple[dict, list[str], float]:
    """``n`` generated inputs of one target, every outcome counted (nothing stops the run): (counts, failures,
    seconds)."""
    warnings.simplefilter("ignore")
    t0 = time.perf_counter()
    tally = ft.Tally()
    work = root / name
    work.mkdir()
    fx = ft.Fixtures(work / "fixtures") if name in COUNTS and list(COUNTS).index(name) < 7 else None
    nfx = fc.NameFixtures(work / "name_fixtures") if fx is None else None
    strategy, check = {
        "policy_bytes": (ft.policy_byte_mutation(), lambda c: ft.check_policy_file(c[0], work, c[1])),
        "policy_meta": (ft.policy_meta_mutation(), lambda c: ft.check_policy_file(c[0], work, c[1])),
        "policy_arrays": (ft.policy_array_mutation(), lambda c: ft.check_policy_file(c[0], work, c[1])),
        "world_json": (ft.world_json_text(), lambda text: ft.check_world_json(text, work, fx.onnx_bare)),
        "onnx": (ft.onnx_mutation(), lambda data: ft.check_onnx(data, work)),
        "cli_export": (ft.st.data(), lambda data: ft.cli_case("export", data, fx, work / "out")),
        "cli_sim": (ft.st.data(), lambda data: ft.cli_case("sim", data, fx, work / "out")),
        "names": (ft.st.data(), lambda data: fc.names_case(data, nfx, work)),
        "run_folders": (ft.st.data(), lambda data: fc.run_folder_case(data, work)),
        "stdout": (ft.st.data(), lambda data: fc.stdout_case(data, nfx, work)),
        "disk_full": (ft.st.data(), lambda data: fc.disk_full_case(data, nfx, work)),
        "weights": (ft.st.data(), lambda data: fc.weights_case(data, work)),
        "part_a": (ft.st.data(), lambda data: fc.part_a_case(data, nfx, work)),
    }[name]

    @ft.fuzz_settings(n)
    @given(case=strategy)
    def t(case):
        tally.add(name, *check(case))
    t()
    return tally.counts.get(name, {o: 0 for o in ft.OUTCOMES}), tally.failures, time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", type=float, default=1.0, help="multiply every target's input count")
    ap.add_argument("--only", default=None, help="comma-separated targets (default all): " + ", ".join(COUNTS))
    ap.add_argument("--jobs", type=int, default=2, help="targets run at once, one process each (default 2)")
    args = ap.parse_args()
    names = args.only.split(",") if args.only else list(COUNTS)
    counts, times, failures = {}, {}, []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="kf-fuzz-all-") as d, ProcessPoolExecutor(max(1, args.jobs)) as pool:
        jobs = {name: pool.submit(run_target, name, max(1, round(COUNTS[name] * args.scale)), Path(d))
                for name in sorted(names, key=lambda n: -COUNTS[n])}
        for name in names:
            counts[name], fails, times[name] = jobs[name].result()
            failures += fails
            print(f"{name}: {sum(counts[name].values())} inputs in {times[name]:.0f} s", flush=True)
    cols = ft.OUTCOMES
    print()
    print(f"| target | inputs | {' | '.join(cols)} | s |")
    print("|---|" + "---:|" * (len(cols) + 2))
    total = {o: 0 for o in cols}
    for name in names:
        c = counts[name]
        for o in cols:
            total[o] += c[o]
        print(f"| {name} | {sum(c.values())} | {' | '.join(str(c[o]) for o in cols)} | {times[name]:.0f} |")
    print(f"| **all** | **{sum(total.values())}** | {' | '.join(f'**{total[o]}**' for o in cols)} | "
          f"{sum(times.values()):.0f} |")
    print(f"\nwall time {time.perf_counter() - t0:.0f} s with {args.jobs} jobs")
    bad = sum(total[o] for o in ft.FAILURES)
    for f in failures[:60]:
        print("\n" + f)
    print(f"\nfailures (tracebacks + hangs + partial outputs + accepted corrupt + unclean messages): {bad}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
