"""The figures every plot and GIF of the project is drawn on (matplotlib Agg, no pyplot state).

Titles, legends and tick labels quote text the user chose: a world name, a policy file's name, a
run's ``exp_name``, a ``--title``. Matplotlib would read ``$...$`` in it as mathtext (a parse error
is an exception at draw time), and a file name that is not UTF-8 (``\\udcff`` from surrogateescape)
cannot be drawn at all. :class:`SafeFigure` makes every text of the figure plain before it is drawn:
escaped by :func:`kiloforge.errors.printable`, cut to :data:`MAX_LABEL` characters, never mathtext
or TeX; characters missing from the font are drawn as boxes and a label too long for the tight layout
keeps the default margins, without a warning on stderr. Every
figure is made by :func:`figure`; :func:`save_png` writes one atomically, :func:`png_bytes` returns
its bytes.
"""
from __future__ import annotations

import io
import os
import warnings
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.text import Text
from matplotlib.ticker import FixedFormatter, Formatter, FuncFormatter

from .errors import printable
from .io import atomic_path

MAX_LABEL = 200  #: characters of one text on a figure (a title quoting a long path is cut)


def plain_label(text: object) -> str:
    """``text`` as a figure shows it: non-printable characters escaped, at most :data:`MAX_LABEL`
    characters (``$`` stays a dollar sign: the figure's texts are never parsed as mathtext).

    >>> plain_label("a$x$\\udcff")
    'a$x$\\\\udcff'
    """
    return printable(text, MAX_LABEL)


class SafeFigure(Figure):
    """A Figure whose texts are plain (:func:`plain_label`, no mathtext, no TeX) whenever it is drawn."""

    def plain_texts(self) -> None:
        """Every text of the figure made plain (before anything measures or draws it)."""
        for t in self.findobj(Text):
            t.set_text(plain_label(t.get_text()))
            t.set_parse_math(False)
            t.set_usetex(False)
        for ax in self.axes:  # tick labels given as text are made again by their formatter at each layout
            for axis in (ax.xaxis, ax.yaxis):
                if isinstance(axis.get_major_formatter(), (FixedFormatter, FuncFormatter)):
                    axis.set_major_formatter(_PlainFormatter(axis.get_major_formatter()))
                if isinstance(axis.get_minor_formatter(), (FixedFormatter, FuncFormatter)):
                    axis.set_minor_formatter(_PlainFormatter(axis.get_minor_formatter()))

    def tight_layout(self, *args: Any, **kwargs: Any) -> None:
        self.plain_texts()
        with _no_glyph_warnings():  # a label too long to fit: the figure keeps its default margins
            warnings.filterwarnings("ignore", message="Tight layout not applied", category=UserWarning)
            super().tight_layout(*args, **kwargs)

    def draw(self, renderer: Any) -> None:
        self.plain_texts()
        with _no_glyph_warnings():
            super().draw(renderer)


class _PlainFormatter(Formatter):
    """Tick labels of another formatter, made plain (:func:`plain_label`)."""

    def __init__(self, inner: Formatter) -> None:
        self.inner = inner

    def __call__(self, x: float, pos: int | None = None) -> str:
        return plain_label(self.inner(x, pos))

    def set_locs(self, locs: Any) -> None:
        self.inner.set_locs(locs)

    def get_offset(self) -> str:
        return plain_label(self.inner.get_offset())


@contextmanager
def _no_glyph_warnings() -> Iterator[None]:
    """Characters the font lacks (a name in another script) are drawn as boxes, without a warning."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"Glyph \d+ .*missing from", category=UserWarning)
        yield


def figure(width_in: float, height_in: float) -> SafeFigure:
    """A new figure on an Agg canvas."""
    fig = SafeFigure(figsize=(width_in, height_in))
    FigureCanvasAgg(fig)
    return fig


def png_bytes(fig: Figure, dpi: int = 110) -> bytes:
    """The figure as PNG bytes (laid out tightly)."""
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return buf.getvalue()


def save_png(fig: Figure, path: str | os.PathLike, dpi: int = 110) -> Path:
    """Write the figure as a PNG atomically (:func:`kiloforge.io.atomic_path`); returns the path."""
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    return Path(path)
