"""SIGINT / SIGTERM during training: stop at the next clean boundary, write a checkpoint, exit 128 + signal.

:class:`StopRequest` installs handlers that only set a flag, which the trainers poll: the MAGDDPG /
MAGRDPG loop at episode-batch boundaries (so the checkpoint resumes exactly), ES between and inside
generations, the guided preparation phases between their steps. A second signal of either kind stops
at once (``KeyboardInterrupt``), keeping the last checkpoint. Handlers can only be installed from the
main thread; elsewhere (e.g. a Ray worker thread) nothing is installed and Ctrl-C arrives as
``KeyboardInterrupt``, which the loop handles the same way.
"""
from __future__ import annotations

import signal
import threading


class Interrupted(Exception):
    """Raised inside the training loop when a stop was requested."""

    def __init__(self, signum: int) -> None:
        super().__init__(f"interrupted by signal {signum}")
        self.signum = signum


class StopRequest:
    """Context manager: ``requested`` is the signal number received (0: none)."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.requested = 0
        self._previous: dict[int, object] = {}

    def _handle(self, signum: int, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = signum

    def __enter__(self) -> "StopRequest":
        if threading.current_thread() is threading.main_thread():
            for s in self.SIGNALS:
                self._previous[s] = signal.signal(s, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        for s, h in self._previous.items():
            signal.signal(s, h)
        self._previous.clear()

    def check(self) -> None:
        """Raise :class:`Interrupted` when a stop was requested."""
        if self.requested:
            raise Interrupted(self.requested)
