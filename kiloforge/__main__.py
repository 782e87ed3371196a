"""``python -m kiloforge``: the ``kiloforge`` command (:mod:`kiloforge.cli`)."""

from .sighold import hold, release  # first: a Ctrl-C or SIGTERM while the imports below load is held

_held, _previous = hold()
try:
    import sys

    from .cli import main
finally:
    release(_previous, program=__name__ == "__main__")

if __name__ == "__main__":
    sys.exit(main(held=_held))
