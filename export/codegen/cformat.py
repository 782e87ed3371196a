"""Format numbers, arrays, identifiers and comment text for the generated C.

The templates only loop and place names; every number and every piece of text that reaches C is
produced here, validated (integers against their C type's range, identifiers against C's rules) or
made comment-safe. Literals never depend on the width of ``int`` (16 bits on AVR, 32 on a host).
"""
from __future__ import annotations

import re
from typing import Iterable

import numpy as np

#: Range of every integer type the firmware uses.
C_RANGES: dict[str, tuple[int, int]] = {
    "int8_t": (-(1 << 7), (1 << 7) - 1),
    "uint8_t": (0, (1 << 8) - 1),
    "int16_t": (-(1 << 15), (1 << 15) - 1),
    "uint16_t": (0, (1 << 16) - 1),
    "int32_t": (-(1 << 31), (1 << 31) - 1),
    "uint32_t": (0, (1 << 32) - 1),
}

C_KEYWORDS = frozenset(
    "auto break case char const continue default do double else enum extern float for goto if inline "
    "int long register restrict return short signed sizeof static struct switch typedef union unsigned "
    "void volatile while _Bool _Complex _Imaginary".split())

_IDENT = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


def c_ident(name: str) -> str:
    """Return ``name`` if it is a valid C identifier (not a keyword, not reserved), else raise.

    >>> c_ident("KF_W0")
    'KF_W0'
    >>> c_ident("0bad")
    Traceback (most recent call last):
    ...
    ValueError: '0bad' is not a valid C identifier
    """
    if not isinstance(name, str) or not _IDENT.match(name) or name in C_KEYWORDS or name.startswith("__"):
        raise ValueError(f"{name!r} is not a valid C identifier")
    return name


def c_int(value: int, ctype: str = "int32_t") -> str:
    """A decimal literal of ``value`` checked against ``ctype``'s range; valid whatever ``int``'s width.

    Unsigned types get a ``u`` suffix (``UL`` beyond 16 bits), 32-bit signed values beyond 16 bits an
    ``L``; INT32_MIN is written as an expression because ``2147483648`` alone is not a signed literal.

    >>> c_int(-5, "int8_t"), c_int(200, "uint8_t"), c_int(70000, "uint32_t"), c_int(-70000)
    ('-5', '200u', '70000UL', '-70000L')
    >>> c_int(-2147483648)
    '(-2147483647L - 1L)'
    >>> c_int(128, "int8_t")
    Traceback (most recent call last):
    ...
    ValueError: 128 does not fit int8_t [-128, 127]
    """
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"c_int needs an integer, got {type(value).__name__}")
    v = int(value)
    if ctype not in C_RANGES:
        raise ValueError(f"unknown C integer type {ctype!r}")
    lo, hi = C_RANGES[ctype]
    if not lo <= v <= hi:
        raise ValueError(f"{v} does not fit {ctype} [{lo}, {hi}]")
    if ctype.startswith("u"):
        return f"{v}UL" if v > 0xFFFF else f"{v}u"
    if v == -(1 << 31):
        return "(-2147483647L - 1L)"
    return f"{v}L" if not -(1 << 15) <= v < (1 << 15) else str(v)


def c_array_body(values: Iterable[int] | np.ndarray, ctype: str, per_line: int = 16, indent: str = "    ") -> str:
    """The comma-separated initialiser lines of an array, ``per_line`` values a line, right-aligned.

    >>> print(c_array_body([1, -2, 300], "int16_t", per_line=2))
          1,  -2,
        300
    """
    vals = [c_int(int(v), ctype) for v in np.asarray(values).ravel()]
    if not vals:
        raise ValueError("C arrays must not be empty")
    width = max(len(v) for v in vals)
    lines = []
    for i in range(0, len(vals), per_line):
        chunk = vals[i:i + per_line]
        lines.append(indent + ", ".join(v.rjust(width) for v in chunk))
    return ",\n".join(lines)


def c_array(name: str, ctype: str, values: Iterable[int] | np.ndarray, *, progmem: bool = True,
            per_line: int = 16, comment: str = "") -> str:
    """A ``static const`` array definition (in flash with ``PROGMEM``), with an optional comment line.

    >>> print(c_array("KF_T", "uint8_t", [1, 2, 3], comment="three bytes"))
    /* three bytes */
    static const uint8_t KF_T[3] PROGMEM = {
        1u, 2u, 3u
    };
    """
    arr = np.asarray(values).ravel()
    head = f"/* {c_comment(comment)} */\n" if comment else ""
    pm = " PROGMEM" if progmem else ""
    return (f"{head}static const {ctype} {c_ident(name)}[{arr.size}]{pm} = {{\n"
            f"{c_array_body(arr, ctype, per_line)}\n}};")


_UNSAFE = re.compile(r"[^ -~]")  # anything but printable ASCII


def c_comment(text: object, max_len: int = 160) -> str:
    """Make free text safe inside a ``/* ... */`` comment on one line (and free of trigraphs).

    Non-printable and non-ASCII characters become ``?``, ``*/`` and ``/*`` are broken up, ``??``
    (trigraph starts) and backslashes (line continuation) are defused, and the text is cut at
    ``max_len`` characters.

    >>> c_comment("evil */ int x; /* \\n\u00e9??=")
    'evil * / int x; / * ? ? ?='
    """
    s = " ".join(str(text).split())  # newlines and runs of whitespace -> one space
    s = _UNSAFE.sub("?", s)
    s = s.replace("\\", "/")
    while "*/" in s or "/*" in s:
        s = s.replace("*/", "* /").replace("/*", "/ *")
    s = s.replace("??", "? ?")
    if len(s) > max_len:
        s = s[: max_len - 3] + "..."
    return s.replace("??", "? ?")


def c_hex_digest(digest: str) -> str:
    """Validate a hex digest (policy hash) for the banner.

    >>> c_hex_digest("AB01")
    'ab01'
    """
    if not isinstance(digest, str) or not re.fullmatch(r"[0-9a-fA-F]{1,128}", digest):
        raise ValueError(f"policy hash must be a hex digest, got {digest!r}")
    return digest.lower()


def clamp_index_table(table: np.ndarray) -> tuple[np.ndarray, int]:
    """Shortest prefix of a table indexed by a uint8 distance that is exact with a clamped index.

    Returns ``(prefix, last)`` such that ``table[..., i] == prefix[..., min(i, last)]`` for every
    ``i``; the C reads ``prefix[d > last ? last : d]``.

    >>> prefix, last = clamp_index_table(np.array([0, 5, 9, 9, 9]))
    >>> prefix.tolist(), last
    ([0, 5, 9], 2)
    """
    t = np.asarray(table)
    flat = t.reshape(-1, t.shape[-1])  # (rows, n)
    n = t.shape[-1]
    last = n - 1
    while last > 0 and np.array_equal(flat[:, last - 1], flat[:, n - 1]):
        last -= 1
    return t[..., : last + 1], last


def nonzero_windows(table: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pack the non-zero window of every row of a (rows, 256) table indexed by a uint8 distance.

    Returns ``(lo, length, offset, packed)``: row k is non-zero only at ``lo[k] .. lo[k]+length[k]-1``
    and ``table[k, lo[k] + i] == packed[offset[k] + i]`` there (``length`` 0 for an all-zero row).

    >>> lo, n, off, packed = nonzero_windows(np.array([[0, 3, 0, 4, 0], [0, 0, 0, 0, 0], [7, 0, 0, 0, 0]]))
    >>> lo.tolist(), n.tolist(), off.tolist(), packed.tolist()
    ([1, 0, 0], [3, 0, 1], [0, 3, 3], [3, 0, 4, 7])
    """
    t = np.asarray(table)
    assert t.ndim == 2, f"nonzero_windows needs a 2-D table, got shape {t.shape}"
    los, lens, offs, parts = [], [], [], []
    pos = 0
    for row in t:
        nz = np.flatnonzero(row)
        a, n = (int(nz[0]), int(nz[-1] - nz[0] + 1)) if nz.size else (0, 0)
        los.append(a)
        lens.append(n)
        offs.append(pos)
        parts.append(row[a:a + n])
        pos += n
    packed = np.concatenate(parts) if pos else np.zeros(1, t.dtype)
    return np.array(los), np.array(lens), np.array(offs), packed

