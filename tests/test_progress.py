"""The one progress bar (kiloforge.progress): tqdm on a terminal, plain lines in a log."""
from __future__ import annotations

import io

from kiloforge.progress import progress_bar


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


def test_terminal_keeps_tqdm_redraws():
    """On a terminal the bar is tqdm's own, redrawn in place with carriage returns."""
    tty = Terminal()
    bar = progress_bar(total=3, desc="t", file=tty)
    bar.update(3)
    bar.close()
    assert "\r" in tty.getvalue() and "3/3" in tty.getvalue()
