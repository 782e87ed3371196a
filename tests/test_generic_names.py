"""The generic layers name no task (issue 42): localisation's words live in the task modules and one compat map."""
from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
GENERIC = ("sim", "learn", "export", "kiloforge", "firmware_templates")
TASK_MODULES = ("sim/tasks/", "firmware_templates/tasks/")
#: the one file that maps the names of files and commands written before tasks were plug-ins
ALLOWED = {"sim/compat.py"}
WORDS = re.compile(r"beacon|coverage|target_uid", re.IGNORECASE)


def test_generic_layers_name_no_task():
    """Outside sim/tasks/ and firmware_templates/tasks/, no source file names beacon, coverage or target uids
    (sim/compat.py, the map of the old names, excepted)."""
    found = []
    for top in GENERIC:
        for path in sorted((ROOT / top).rglob("*")):
            rel = path.relative_to(ROOT).as_posix()
            if path.suffix not in (".py", ".c", ".h", ".j2") or rel.startswith(TASK_MODULES) or rel in ALLOWED:
                continue
            if WORDS.search(path.read_text(encoding="utf-8")):
                found.append(rel)
    assert found == []
