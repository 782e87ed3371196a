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


@pytest.fixture(scope="module")
def ray_session(tmp_path_factory):
    """A local Ray with 2 CPUs for one test module, its temp files under pytest's tmp path; shut down afterwards
    (code under test that finds Ray running joins it and leaves it running)."""
    import logging

    ray = pytest.importorskip("ray")
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False,
             logging_level=logging.ERROR, _temp_dir=str(tmp_path_factory.mktemp("ray")))
    yield
    ray.shutdown()
