"""The Jinja environment over ``firmware_templates/`` and the inliner of its hand-written C.

Templates are thin (``StrictUndefined``; they only loop and place names); every number and every
piece of text that reaches C is formatted by :mod:`export.codegen.cformat`.
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Iterable

import jinja2

from sim.features import TASK_FEATURES

TEMPLATE_DIR = Path(__file__).resolve().parent.parent.parent / "firmware_templates"

_TASK_BLOCK = re.compile(r"features/([a-z][a-z0-9_]*)\.c\.j2")
_LOCAL_INCLUDE = re.compile(r'^\s*#\s*include\s+"([A-Za-z0-9_./]+)"\s*$')


class _RecordingLoader(jinja2.FileSystemLoader):
    """A FileSystemLoader that remembers which templates were loaded (a test checks that each is used)."""

    loaded: set[str] = set()

    def get_source(self, environment: jinja2.Environment, template: str) -> tuple[str, str | None, Any]:
        _RecordingLoader.loaded.add(template)
        try:
            return super().get_source(environment, template)
        except jinja2.TemplateNotFound:
            own = _TASK_BLOCK.fullmatch(template)
            tf = TASK_FEATURES.get(own.group(1)) if own else None
            if tf is None:
                raise
            return tf.table.template(), None, lambda: False  # a task's own feature (sim.table_features)


def environment() -> jinja2.Environment:
    """The environment every program is rendered with."""
    return jinja2.Environment(loader=_RecordingLoader(str(TEMPLATE_DIR)), undefined=jinja2.StrictUndefined,
                              autoescape=False, keep_trailing_newline=True, trim_blocks=True,
                              lstrip_blocks=True)


def templates_loaded() -> frozenset[str]:
    """Names of every template loaded by a render in this process (for the test that every template is used)."""
    return frozenset(_RecordingLoader.loaded)


def inline_sources(names: Iterable[str], template_dir: Path = TEMPLATE_DIR) -> str:
    """Hand-written C files concatenated, each local ``#include "..."`` replaced by the included file.

    A tiny preprocessor for our own files only: a file of ``template_dir`` is pasted where it is
    first included (or named in ``names``) and its later includes are dropped, so the result needs
    no file of ours beside it. System includes (``<...>``) stay.
    """
    done: set[Path] = set()
    root = template_dir.resolve()

    def paste(path: Path) -> str:
        path = path.resolve()
        if path in done:
            return ""
        done.add(path)
        out = [f"/* ---- firmware_templates/{path.relative_to(root).as_posix()} ---- */"]
        for line in path.read_text(encoding="utf-8").splitlines():
            m = _LOCAL_INCLUDE.match(line)
            if m:
                inc = (path.parent / m.group(1)).resolve()
                if inc.is_file() and root in inc.parents:
                    out.append(paste(inc).rstrip("\n"))
                    continue
            out.append(line)
        return "\n".join(out).strip("\n") + "\n"

    return "\n".join(paste(template_dir / name) for name in names)
