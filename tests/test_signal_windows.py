"""A Ctrl-C or SIGTERM at any line of the entry-point plumbing (the ``__main__`` modules, the console scripts,
kiloforge.cli, kiloforge.interrupts, the start of each command's ``main``) ends in one line and 130 / 143, or, once the
command is done, in its own exit status: never a traceback (tests/signal_at_line.py raises the signal)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = Path(__file__).with_name("signal_at_line.py")
ENV = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONWARNINGS="ignore")
PLUMBING = "kiloforge/cli.py,kiloforge/interrupts.py"

#: name: (package, its traced functions, arguments, exit status uninterrupted, every how many lines)
CASES = {
    "export": ("export", "export/__main__.py,export/cli/main.py:main",
               ["--out", "kilobot_policy.c", "--seed", "2", "--robots-calib", "2", "--calib-steps", "4",
                "--no-avr", "--quiet"], 0, 1),
    "kiloforge export": ("kiloforge", "kiloforge/__main__.py,export/__main__.py,export/cli/main.py:main",
                         ["export", "--out", "kilobot_policy.c", "--seed", "2", "--robots-calib", "2",
                          "--calib-steps", "4", "--no-avr", "--quiet"], 0, 3),
    "kiloforge-export": ("kiloforge.scripts:export", "kiloforge/scripts.py,export/__main__.py,export/cli/main.py:main",
                         ["--out", "kilobot_policy.c", "--seed", "2", "--robots-calib", "2", "--calib-steps", "4",
                          "--no-avr", "--quiet"], 0, 3),
    "sim": ("sim", "sim/__main__.py,kiloforge/sim_cli.py:main", ["--help"], 0, 4),
    # learn imports torch for every command (seconds a run): a sample of its lines
    "learn": ("learn", "learn/__main__.py:<module>,learn/__main__.py:main,learn/__main__.py:_main",
              ["plot", "no-such-run"], 2, 25),
}


def run(tmp: Path, sig: str, n: int, case: str) -> subprocess.CompletedProcess:
    package, traced, args, _, _ = CASES[case]
    d = tmp / f"{sig}-{n}"
    d.mkdir()
    return subprocess.run([sys.executable, str(SCRIPT), sig, str(n), f"{traced},{PLUMBING}", package, *args],
                          cwd=d, env=ENV, capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("case", CASES)
def test_a_signal_at_any_plumbing_line_ends_in_one_line(tmp_path, case):
    """Every traced line (or every k-th, alternating SIGINT and SIGTERM): exit 130 / 143 with a last line saying
    'interrupted', or the uninterrupted status; no traceback in any."""
    clean = run(tmp_path, "SIGINT", 0, case)
    status, stride = CASES[case][3], CASES[case][4]
    assert clean.returncode == status, clean.stderr
    lines = int(clean.stderr.rsplit("lines: ", 1)[1])
    assert lines > 100, clean.stderr  # the tracing saw the plumbing run
    moments = [(("SIGINT", "SIGTERM")[i % 2], n) for i, n in enumerate(range(1, lines + 1, stride))]
    with ThreadPoolExecutor(max(1, min(4, os.cpu_count() or 1))) as pool:
        results = list(pool.map(lambda m: (m, run(tmp_path, *m, case)), moments))
    problems = []
    for (sig, n), r in results:
        err = r.stderr.strip()
        stopped = r.returncode == 128 + signal.Signals[sig]
        if "Traceback" in err or not (stopped or r.returncode == status):
            problems.append(f"{sig} at line {n}: exit {r.returncode}: {err[-600:]}")
        elif stopped and "interrupted" not in err.splitlines()[-1]:
            problems.append(f"{sig} at line {n}: exit {r.returncode} without saying so: {err[-300:]}")
    assert not problems, f"{len(problems)} of {len(moments)}:\n" + "\n".join(problems[:5])
    assert any(r.returncode != status for _, r in results)  # some signals did stop the command


@pytest.mark.parametrize("outcome", ["return", "error"])
def test_in_process_callers_get_their_handlers_back(outcome):
    """run_entry_point called in-process (argv given) leaves the caller's SIGINT / SIGTERM handlers as they were,
    whether the command returns or raises; inside the command a signal raises."""
    from kiloforge.interrupts import Interrupted, run_entry_point

    seen = []

    def command(argv):
        for s in (signal.SIGINT, signal.SIGTERM):
            try:
                signal.getsignal(s)(s, None)
            except KeyboardInterrupt as e:
                seen.append(type(e))
        if outcome == "error":
            raise ValueError("bad input")
        return 7

    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    if outcome == "return":
        assert run_entry_point(lambda: command, [], "interrupted") == 7
    else:
        with pytest.raises(ValueError):
            run_entry_point(lambda: command, [], "interrupted")
    assert seen == [KeyboardInterrupt, Interrupted]
    assert {s: signal.getsignal(s) for s in before} == before


def test_importing_the_console_scripts_module_leaves_handlers_alone():
    """kiloforge.scripts holds signals only under a script wrapper: imported by a test, the handlers stay."""
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    r = subprocess.run([sys.executable, "-c", "import signal, kiloforge.scripts; "
                        "print(signal.getsignal(signal.SIGINT) is signal.default_int_handler)"],
                       env=ENV, capture_output=True, text=True, timeout=60)
    import kiloforge.scripts  # noqa: F401

    assert {s: signal.getsignal(s) for s in before} == before
    assert r.stdout.strip() == "True", r.stderr
