"""Test-session isolation shared by every test module."""
import signal

import pytest


@pytest.fixture(autouse=True)
def default_signal_handlers():
    """Each test starts with Python's default SIGINT / SIGTERM handling and gets it back afterwards: an
    entry point run in-process as the program (argv None) ignores both once it has returned, as a program
    about to exit should, which must not reach the next test."""
    defaults = {signal.SIGINT: signal.default_int_handler, signal.SIGTERM: signal.SIG_DFL}
    for s, h in defaults.items():
        signal.signal(s, h)
    yield
    for s, h in defaults.items():
        signal.signal(s, h)
