"""A task's own observation features: computed each control period from the robot's neighbour table.

A task file declares them in :attr:`sim.tasks.Task.own_features` and lists their names in ``features`` like any
built-in one; resolving the task registers them (:func:`register`), and from then on the simulator, the
firmware and the emulator treat them as they treat the built-ins. One feature has three parts, kept equal by
the verification ladder (``export --verify host | avr``, bit for bit, and ``export verify``, int8 against float):

* ``reference(table, cfg)``: the float value the simulator gives the actor, (n, width) float64 in [-1, 1];
* ``integer(table, one)``: the emulator twin, (n, width) integers in -128..127: the int8 inputs the firmware
  writes, ``one`` being the quantised 1.0 (``KF_ONE``);
* ``firmware``: the C statements of the firmware's ``kf_observe`` that compute the same integers. They may read
  ``s->nbr_count`` (uint8_t, the entries heard this period) and ``s->nbr[i].dist`` (uint8_t, mm), use the loop
  counter ``i`` (uint8_t, declared for them) and the constants ``KF_ONE`` (int8_t) and ``KF_NBR_CAPACITY``, and
  must write ``obs[KF_OBS_<NAME> + j]`` (int8_t) for every j < width. ``firmware_decl`` holds local declarations.

The table is what a robot heard in the period: one entry per sender (the latest distance), at most the world's
``neighbour_table_size``. The order of its entries is not part of the contract (the firmware keeps arrival order,
the simulator sender order): a feature must give the same result for any order (counts, minima, integer sums).

    >>> t = NeighbourTable.of(np.array([0, 0, 2]), np.array([40.0, 25.0, 90.0]), 3)
    >>> t.count().tolist(), t.min(t.dist_mm, empty=-1.0).tolist()
    ([2, 0, 1], [25.0, -1.0, 90.0])
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from kiloforge.errors import InputError

#: a feature's name becomes a C identifier (``KF_OBS_<NAME>``) and an ONNX input name
FEATURE_NAME = re.compile(r"[a-z][a-z0-9_]{0,23}")
MAX_WIDTH = 8  #: inputs one task feature may add
_C_TEXT = re.compile(r"[\x20-\x7e\t\n]*")  #: printable ASCII, tabs and newlines


@dataclass(frozen=True)
class NeighbourTable:
    """Every robot's table of one period, flattened: entry k belongs to robot ``robot[k]`` (0..n-1), heard at
    ``dist_mm[k]``. Entries are sorted by robot, then distance (:meth:`of`)."""

    robot: np.ndarray  # (K,) int64
    dist_mm: np.ndarray  # (K,) float64
    n: int  # robots (rows of a feature's result)

    @classmethod
    def of(cls, robot: np.ndarray, dist_mm: np.ndarray, n: int) -> "NeighbourTable":
        robot = np.asarray(robot, np.int64).ravel()
        dist = np.asarray(dist_mm, np.float64).ravel()
        order = np.lexsort((dist, robot))
        return cls(robot.take(order), dist.take(order), int(n))

    def count(self) -> np.ndarray:
        """(n,) int64: entries per robot."""
        return np.bincount(self.robot, minlength=self.n)

    def min(self, values: np.ndarray, empty: float) -> np.ndarray:
        """(n,) the least of ``values`` (K,) per robot, ``empty`` for a robot with no entry."""
        return self._reduce(np.minimum, values, empty)

    def max(self, values: np.ndarray, empty: float) -> np.ndarray:
        """(n,) the greatest of ``values`` (K,) per robot, ``empty`` for a robot with no entry."""
        return self._reduce(np.maximum, values, empty)

    def sum(self, values: np.ndarray) -> np.ndarray:
        """(n,) the sum of ``values`` (K,) per robot, 0 for a robot with no entry."""
        return self._reduce(np.add, values, 0)

    def _reduce(self, ufunc: np.ufunc, values: np.ndarray, empty: float) -> np.ndarray:
        v = np.asarray(values)
        assert v.shape == self.robot.shape, f"values must be ({self.robot.size},), one per entry, got {v.shape}"
        cnt = self.count()
        out = np.full(self.n, empty, np.result_type(v, np.asarray(empty)))
        has = cnt > 0
        if v.size:  # entries are grouped by robot: one segment per robot with entries
            out[has] = ufunc.reduceat(v, (np.cumsum(cnt) - cnt)[has])
        return out


class TableFeature:
    """Base of a task's own feature (the module doc says what each part must do). Subclass it and set
    ``name``, ``doc``, ``width`` (1 .. 8), ``firmware`` (and ``firmware_decl``); implement ``reference`` and
    ``integer``."""

    name: ClassVar[str] = ""
    doc: ClassVar[str] = ""  #: one line: what the input says (tables, ONNX metadata)
    width: ClassVar[int] = 1
    firmware: ClassVar[str] = ""  #: C statements of kf_observe (module doc)
    firmware_decl: ClassVar[str] = ""  #: C declarations at the top of kf_observe

    def reference(self, table: NeighbourTable, cfg: Any) -> np.ndarray:
        raise NotImplementedError

    def integer(self, table: NeighbourTable, one: int) -> np.ndarray:
        raise NotImplementedError

    # --- used by the tools, through the checks below -------------------------------------------------------
    def float_values(self, table: NeighbourTable, cfg: Any) -> np.ndarray:
        """``reference`` checked: (n, width) finite float64 in [-1, 1]; InputError in one line otherwise."""
        out = self._call("reference", table, cfg)
        ok = np.issubdtype(out.dtype, np.number) and np.all(np.isfinite(out)) and np.all(np.abs(out) <= 1.0)
        if not ok:
            raise InputError(f"feature {self.name!r}: reference() must return finite numbers in [-1, 1]")
        return out.astype(np.float64)

    def int_values(self, table: NeighbourTable, one: int) -> np.ndarray:
        """``integer`` checked: (n, width) int64 in -128..127; InputError in one line otherwise."""
        out = self._call("integer", table, int(one))
        if not (np.issubdtype(out.dtype, np.integer) and np.all((out >= -128) & (out <= 127))):
            raise InputError(f"feature {self.name!r}: integer() must return integers in -128..127, got {out.dtype}")
        return out.astype(np.int64)

    def _call(self, method: str, table: NeighbourTable, arg: Any) -> np.ndarray:
        try:
            out = np.asarray(getattr(self, method)(table, arg))
        except InputError:
            raise
        except Exception as e:
            raise InputError(f"feature {self.name!r}: {method}() raised {type(e).__name__}: {e}") from None
        if out.shape != (table.n, self.width):
            raise InputError(f"feature {self.name!r}: {method}() must return shape ({table.n}, {self.width}), "
                             f"got {out.shape}")
        return out

    def template(self) -> str:
        """The feature's firmware block in the form of ``firmware_templates/features/<name>.c.j2`` (Jinja macros
        head, decl, code), its C text taken verbatim."""
        def raw(text: str) -> str:
            return "{% raw %}" + text + "{% endraw %}"

        return ("{% macro head() %}{% endmacro %}\n"
                "{% macro decl() %}" + raw(self.firmware_decl) + "{% endmacro %}\n"
                "{% macro code() %}" + raw(self.firmware) + "{% endmacro %}\n")


def check(feature: object, where: str, builtin: set[str]) -> TableFeature:
    """``feature`` (an instance or a class of :class:`TableFeature`) checked; InputError naming ``where``."""
    f = feature() if isinstance(feature, type) and issubclass(feature, TableFeature) else feature
    if not isinstance(f, TableFeature):
        raise InputError(f"{where}: own_features must hold sim.tasks.TableFeature subclasses, "
                         f"got {type(feature).__name__}")
    name = f.name
    if not (isinstance(name, str) and FEATURE_NAME.fullmatch(name)):
        raise InputError(f"{where}: feature name {name!r} must match {FEATURE_NAME.pattern} (it names C identifiers)")
    at = f"{where}: feature {name!r}"
    if name in builtin:
        raise InputError(f"{at} has the name of a built-in feature; choose another")
    if not (isinstance(f.width, int) and not isinstance(f.width, bool) and 1 <= f.width <= MAX_WIDTH):
        raise InputError(f"{at}: width must be an integer in 1..{MAX_WIDTH}, got {f.width!r}")
    if not (isinstance(f.doc, str) and f.doc and "\n" not in f.doc):
        raise InputError(f"{at}: doc must be one line of text")
    for part in ("firmware", "firmware_decl"):
        text = getattr(f, part)
        if not isinstance(text, str):
            raise InputError(f"{at}: {part} must be C text, got {type(text).__name__}")
        if not _C_TEXT.fullmatch(text) or "{%" in text or "%}" in text:
            raise InputError(f"{at}: {part} must be printable ASCII C without '{{%' or '%}}'")
    if not f.firmware.strip():
        raise InputError(f"{at} has no firmware block (the C statements that compute it on the robot); "
                         "see docs/tasks.md")
    if f"KF_OBS_{name.upper()}" not in f.firmware:
        raise InputError(f"{at}: its firmware block never writes obs[KF_OBS_{name.upper()}]")
    for method in ("reference", "integer"):
        if getattr(type(f), method) is getattr(TableFeature, method):
            raise InputError(f"{at} does not define {method}() (see docs/tasks.md)")
    return f
