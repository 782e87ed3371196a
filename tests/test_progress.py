"""The one progress bar (kiloforge.progress): tqdm on a terminal, plain lines in a log."""
from __future__ import annotations

import io
import re
import subprocess
import sys
from pathlib import Path

from kiloforge.progress import LINE_INTERVAL_S, progress_bar

ROOT = Path(__file__).resolve().parents[1]


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_log_gets_plain_lines():
    """Redirected, a kept bar writes whole lines without carriage returns or escapes, the last one at 100 %."""
    log = io.StringIO()
    bar = progress_bar(total=200, desc="train", unit="step", file=log)
    for _ in range(200):
        bar.update(1)
    bar.close()
    text = log.getvalue()
    assert "\r" not in text and "\x1b" not in text and text.endswith("\n")
    lines = text.splitlines()
    assert all(line.strip() for line in lines)
    assert lines[-1].startswith("train: 100%") and "200/200" in lines[-1]
    assert len(lines) <= 3  # the first line, at most one more within the interval, the last


def test_log_transient_and_nested_bars_write_no_redraws():
    """Redirected, a transient bar inside a kept one leaves no blank lines, \\r or cursor moves."""
    log = io.StringIO()
    outer = progress_bar(total=2, desc="outer", file=log)
    inner = progress_bar(total=5, desc="inner", leave=False, file=log)
    inner.update(5)
    inner.close()
    outer.update(2)
    outer.close()
    text = log.getvalue()
    assert "\r" not in text and "\x1b" not in text
    assert all(line.strip() for line in text.splitlines())
    assert text.splitlines()[-1].startswith("outer: 100%")
    assert any(line.startswith("inner: 100%") for line in text.splitlines())  # a log keeps what a transient bar did


def test_redirected_short_command_logs_its_progress(tmp_path):
    """A redirected `python -m learn evaluate` of a second logs lines with nonzero progress (at least one
    every LINE_INTERVAL_S <= 10 s, and the last at 100 %), not only `0%| 0/N`."""
    assert LINE_INTERVAL_S <= 10
    policy = ROOT / "export" / "data" / "default_policy.npz"
    r = subprocess.run([sys.executable, "-m", "learn", "evaluate", "--policy", str(policy), "--robots", "2",
                        "--episodes", "2", "--steps", "30", "--no-baselines"], cwd=tmp_path, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    done = [line for line in r.stderr.splitlines() if re.search(r"\b([1-9]\d*)%\|", line)]
    assert done and "30/30" in done[-1], r.stderr


def test_terminal_keeps_tqdm_redraws():
    """On a terminal the bar is tqdm's own, redrawn in place with carriage returns."""
    tty = Terminal()
    bar = progress_bar(total=3, desc="t", file=tty)
    bar.update(3)
    bar.close()
    assert "\r" in tty.getvalue() and "3/3" in tty.getvalue()


class Clock:
    """A settable time.perf_counter for the budget bar."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def test_budget_bar_total_is_the_time_budget(monkeypatch):
    """With max_seconds the bar's total is the time budget and it stands at the larger share spent."""
    clock = Clock()
    monkeypatch.setattr("kiloforge.progress.time.perf_counter", clock)
    bar = progress_bar(total=1000, unit="step", max_seconds=600, file=io.StringIO())
    assert bar.bar.total == 600 and bar.bar.n == 0
    bar.update(500)  # half the steps, no time yet: the steps bind
    assert bar.bar.n == 300
    clock.now += 450  # 75 % of the time: the time binds (the run stops at the budget, not at 1000 steps)
    bar.update(10)
    assert bar.bar.n == 450 and bar.fraction() == 0.75
    clock.now += 1000  # past the budget: full, never beyond
    bar.update(10)
    assert bar.bar.n == 600
    bar.close()


def test_budget_bar_counts_an_earlier_session(monkeypatch):
    """A resumed run's bar starts at the time already spent (``elapsed``) and shows the work as x/total."""
    monkeypatch.setattr("kiloforge.progress.time.perf_counter", Clock())
    log = io.StringIO()
    bar = progress_bar(total=200, initial=20, unit="gen", desc="es", max_seconds=100, elapsed=40, file=log)
    assert bar.bar.n == 40 and bar.fraction() == 0.4
    bar.set_postfix_str("fitness 0.5")
    bar.close()
    text = log.getvalue()
    assert "\r" not in text and "20/200 gen" in text and "fitness 0.5" in text


def test_budget_bar_in_a_log_writes_plain_lines():
    """Redirected, a time-budget bar writes whole lines (no \\r), the last with the work done."""
    log = io.StringIO()
    bar = progress_bar(total=50, unit="step", desc="train", max_seconds=3600, file=log)
    for _ in range(50):
        bar.update(1)
    bar.close()
    text = log.getvalue()
    assert "\r" not in text and "\x1b" not in text and text.endswith("\n")
    assert text.splitlines()[-1].startswith("train: 100%") and "50/50 step" in text.splitlines()[-1]


def test_without_a_time_budget_the_bar_is_plain_tqdm():
    """max_seconds 0 (no --max-minutes) is the ordinary bar over the work."""
    bar = progress_bar(total=7, unit="step", max_seconds=0, file=io.StringIO())
    assert bar.total == 7 and not hasattr(bar, "fraction")
    bar.close()
