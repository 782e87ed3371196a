"""``python -m kiloforge``: the ``kiloforge`` command (:mod:`kiloforge.cli`)."""

import _signal  # built in: a Ctrl-C or SIGTERM while the imports below load is held back (kiloforge.interrupts)

_held: list[int] = []
_previous = {_s: _signal.signal(_s, lambda signum, frame: _held.append(signum))
             for _s in (_signal.SIGINT, _signal.SIGTERM)}
try:
    import sys

    from .cli import main
finally:
    if __name__ != "__main__":  # run as the program: held until kiloforge.interrupts.run_entry_point takes over
        for _s, _h in _previous.items():
            _signal.signal(_s, _signal.default_int_handler if _h is None else _h)

if __name__ == "__main__":
    sys.exit(main(held=_held))
