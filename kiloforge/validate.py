"""Validation of every external input: files, JSON documents, ``.npz`` archives and typed values.

Every loader of the project reads what it did not write itself through these functions: policy
artifacts (:mod:`kiloforge.artifact`), world configurations (:class:`sim.config.WorldConfig` checks
its own field types here), world JSON files and ONNX models (:mod:`export.interop.onnx_import`),
checkpoints, and the numbers of every command line. The rules:

* **regular files only** (:func:`read_regular_file`): a directory, a FIFO, a device such as
  ``/dev/zero`` or a socket is refused before it is read, and at most ``max_bytes + 1`` bytes are
  ever read, so an endless or huge input cannot exhaust memory;
* **limits before allocation**: JSON nesting depth and size are measured on the text before it is
  parsed (:func:`parse_json`); an ``.npz`` archive's member count, directory size and every
  member's uncompressed size are read from the zip directory, and every ``.npy`` header is parsed
  and checked against its member's size, before any member is decompressed or any array allocated
  (:func:`read_npz`);
* **exact types**: an integer field takes only integers (not ``11.0``, not ``true``), a number only
  finite numbers (JSON's ``NaN`` / ``Infinity`` and overflowing literals such as ``1e999`` are
  refused at parse time), a boolean only ``true`` / ``false`` (never ``"true"``), a string only a
  string (:func:`check_int`, :func:`check_real`, :func:`check_bool`, :func:`check_str`,
  :func:`check_typed` for dataclass fields);
* every failure is one :class:`~kiloforge.errors.InputError` line that names the file and the field.
"""
from __future__ import annotations

import argparse
import io
import json
import math
import os
import re
import stat
import struct
import zipfile
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .errors import InputError, printable

MIB = 1 << 20
MAX_JSON_BYTES = 4 * MIB  #: a JSON document (policy meta, world file, config) larger than this is refused
MAX_JSON_DEPTH = 64  #: nesting of arrays and objects (the deepest kiloforge writes is 4)
MAX_POLICY_BYTES = 32 * MIB  #: a policy file; the largest Kilobot policy is a few tens of KB
MAX_NPZ_MEMBERS = 64  #: arrays in one policy file (an LSTM artifact has 8)
MAX_ZIP_DIRECTORY_BYTES = 256 * 1024  #: the zip central directory (64 members need under 20 KB)
MAX_NPZ_BYTES = 64 * MIB  #: all members together, uncompressed
MAX_NPY_HEADER = 4096  #: an .npy header (numpy writes 128 bytes for a plain array)
MAX_TEXT = 200  #: characters of file-provided text quoted in one message

_MEMBER_NAME = re.compile(r"[A-Za-z0-9_]{1,64}\.npy")
_ARRAY_KINDS = "fiub"  #: float, signed, unsigned, bool: what a policy file may hold (no objects, no complex)


def quote(text: object) -> str:
    """File-provided text for a message: escaped (:func:`kiloforge.errors.printable`), cut, in quotes."""
    return f"'{printable(text, MAX_TEXT)}'"


def show(value: Any) -> str:
    """A value and its type for a message: ``11.0 (a float)``, ``'true' (a string)``, ``true (a boolean)``."""
    if isinstance(value, (bool, np.bool_)):
        kind = "a boolean"
    elif isinstance(value, (int, np.integer)):
        kind = "an integer"
    elif isinstance(value, (float, np.floating)):
        kind = "a float"
    elif isinstance(value, str):
        kind = "a string"
    elif value is None:
        return "null"
    elif isinstance(value, dict):
        kind = "an object"
    elif isinstance(value, (list, tuple)):
        kind = "a list"
    else:
        kind = type(value).__name__
    text = json.dumps(value) if isinstance(value, (bool, type(None))) else repr(value)
    return f"{printable(text, 60)} ({kind})"


# --- typed values --------------------------------------------------------------------------------
def _num(x: float) -> str:
    return str(x) if isinstance(x, int) else f"{x:g}"


def _range(v: float, where: str, lo: float | None, hi: float | None, lo_open: bool, hi_open: bool) -> None:
    low_bad = lo is not None and (v <= lo if lo_open else v < lo)
    high_bad = hi is not None and (v >= hi if hi_open else v > hi)
    if low_bad or high_bad:
        left = "-inf" if lo is None else _num(lo)
        right = "inf" if hi is None else _num(hi)
        span = f"{'(' if lo_open or lo is None else '['}{left}, {right}{')' if hi_open or hi is None else ']'}"
        raise InputError(f"{where} must be in {span}, got {v!r}")


def check_int(value: Any, where: str, lo: int | None = None, hi: int | None = None) -> int:
    """``value`` as an int if it is an integer (not a bool, not a float such as 11.0) in ``[lo, hi]``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise InputError(f"{where} must be an integer, got {show(value)}")
    v = int(value)
    _range(v, where, lo, hi, False, False)
    return v


def check_real(value: Any, where: str, lo: float | None = None, hi: float | None = None, *,
               lo_open: bool = False, hi_open: bool = False) -> float | int:
    """``value`` if it is a finite number (an integer or a float, never a bool) in the given range.

    Integers are kept as they are (a world written as ``250`` hashes as ``250``); NumPy scalars
    become Python numbers.
    """
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InputError(f"{where} must be a number, got {show(value)}")
    try:
        f = float(value)
    except OverflowError:
        raise InputError(f"{where} must be a finite number, got an integer of {len(str(abs(int(value))))} digits") from None
    if not math.isfinite(f):
        raise InputError(f"{where} must be a finite number, got {f!r}")
    _range(f, where, lo, hi, lo_open, hi_open)
    if isinstance(value, (int, np.integer)):
        return int(value)
    return f


def check_bool(value: Any, where: str) -> bool:
    """``value`` if it is a boolean (``true`` / ``false``; never 0, 1 or a string such as "true")."""
    if not isinstance(value, (bool, np.bool_)):
        raise InputError(f"{where} must be true or false, got {show(value)}")
    return bool(value)


def check_str(value: Any, where: str, max_len: int = 256, *, printable_only: bool = True) -> str:
    """``value`` if it is a string of at most ``max_len`` characters (without control characters)."""
    if not isinstance(value, str):
        raise InputError(f"{where} must be a string, got {show(value)}")
    if len(value) > max_len:
        raise InputError(f"{where} must be at most {max_len} characters, got {len(value)}")
    if printable_only and not value.isprintable():
        raise InputError(f"{where} must not hold control characters, got {quote(value)}")
    return value


def check_typed(value: Any, type_name: str, where: str) -> Any:
    """``value`` checked against a dataclass field annotation (``"int"``, ``"float"``, ``"bool"``,
    ``"str"``); returns it normalised (NumPy scalars become Python values)."""
    if type_name == "int":
        return check_int(value, where)
    if type_name == "float":
        return check_real(value, where)
    if type_name == "bool":
        return check_bool(value, where)
    if type_name == "str":
        return check_str(value, where)
    raise TypeError(f"{where}: no check for fields of type {type_name}")


def check_keys(obj: dict, where: str, allowed: set[str] | frozenset[str]) -> None:
    """Refuse keys outside ``allowed`` (naming them)."""
    unknown = sorted(str(k) for k in obj if k not in allowed)
    if unknown:
        raise InputError(f"{where}: unknown field(s) {', '.join(quote(k) for k in unknown[:8])}")


# --- command-line numbers ------------------------------------------------------------------------
_DECIMAL = re.compile(r"-?[0-9]{1,30}")  # [0-9], not \d: ASCII digits only


def parse_decimal(text: str) -> int:
    """``text`` as a decimal integer: ASCII digits ``0-9`` with an optional leading ``-``, blanks around it
    allowed, at most 30 digits; ValueError for anything else that ``int()`` would take (``+3``, ``1_0``,
    Arabic-Indic or other Unicode digits, inner spaces).

    >>> parse_decimal(" 42 "), parse_decimal("-7")
    (42, -7)
    >>> parse_decimal("1_0")
    Traceback (most recent call last):
    ValueError: not a decimal integer: '1_0'
    """
    t = text.strip(" \t\r\n")
    if not _DECIMAL.fullmatch(t):
        raise ValueError(f"not a decimal integer: {quote(text)}")
    return int(t)


def int_arg(lo: int | None = None, hi: int | None = None) -> Callable[[str], int]:
    """An argparse ``type``: a decimal integer (:func:`parse_decimal`) in ``[lo, hi]`` (one-line error otherwise)."""
    def parse(text: str) -> int:
        try:
            v = parse_decimal(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer (ASCII digits), got {quote(text)}") from None
        try:
            return check_int(v, "the value", lo, hi)
        except InputError as e:
            raise argparse.ArgumentTypeError(str(e).removeprefix("the value ")) from None
    parse.__name__ = "integer"
    return parse


def float_arg(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
              hi_open: bool = False) -> Callable[[str], float]:
    """An argparse ``type``: a finite number in the range (``nan``, ``inf``, ``1e999`` are refused)."""
    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {quote(text)}") from None
        try:
            return float(check_real(v, "the value", lo, hi, lo_open=lo_open, hi_open=hi_open))
        except InputError as e:
            raise argparse.ArgumentTypeError(str(e).removeprefix("the value ")) from None
    parse.__name__ = "number"
    return parse


SEED_MAX = 2 ** 63 - 1  #: seeds are non-negative (numpy.random.SeedSequence)
seed_arg = int_arg(0, SEED_MAX)


# --- files ---------------------------------------------------------------------------------------
def read_regular_file(path: str | os.PathLike, what: str, max_bytes: int, *, dir_hint: str | None = None) -> bytes:
    """The bytes of ``path`` if it is a regular file of at most ``max_bytes``; raises InputError.

    ``what`` names the file in messages (``policy file``); ``dir_hint``: a file name to suggest when
    ``path`` is a directory that holds it (``policy_best.npz``). The file is opened without blocking
    and checked again after opening, so a FIFO or a device is never read.
    """
    path = Path(path)
    name = f"{what} {quote(path)}"
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise InputError(f"{name} does not exist") from None
    except OSError as e:
        raise InputError(f"{name} cannot be read ({printable(e.strerror or e)})") from None
    if stat.S_ISDIR(st.st_mode):
        hint = ""
        if dir_hint and (path / dir_hint).is_file():
            hint = f"; did you mean {quote(path / dir_hint)}?"
        raise InputError(f"{name} is a directory, not a file{hint}")
    if not stat.S_ISREG(st.st_mode):
        kind = ("a FIFO" if stat.S_ISFIFO(st.st_mode) else "a device" if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode)
                else "a socket" if stat.S_ISSOCK(st.st_mode) else "not a regular file")
        raise InputError(f"{name} is {kind}; give a regular file")
    if st.st_size > max_bytes:
        raise InputError(f"{name} is {st.st_size:,} bytes, more than the {max_bytes:,} allowed")
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0))
    except OSError as e:
        raise InputError(f"{name} cannot be read ({printable(e.strerror or e)})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):  # replaced between the two looks
            raise InputError(f"{name} is not a regular file")
        with os.fdopen(fd, "rb", closefd=False) as f:
            data = f.read(min(st.st_size, max_bytes) + 1)  # one byte more shows a file that grew past the limit
    except OSError as e:
        raise InputError(f"{name} cannot be read ({printable(e.strerror or e)})") from None
    finally:
        os.close(fd)
    if len(data) > max_bytes:
        raise InputError(f"{name} is larger than the {max_bytes:,} bytes allowed")
    return data


# --- JSON ----------------------------------------------------------------------------------------
_JSON_STRING = re.compile(r'"(?:[^"\\]|\\.)*"', re.S)
_OPEN, _CLOSE = frozenset(b"[{"), frozenset(b"]}")


def json_depth(text: str) -> int:
    """The deepest nesting of arrays and objects in JSON text (brackets inside strings ignored);
    linear time, no recursion, nothing parsed.

    >>> json_depth('{"a": [1, {"b": "]]"}]}')
    3
    """
    brackets = re.sub(r"[^\[\]{}]", "", _JSON_STRING.sub("", text))
    if not brackets:
        return 0
    b = np.frombuffer(brackets.encode("ascii"), np.uint8)
    steps = np.where((b == ord("[")) | (b == ord("{")), 1, -1)
    return int(np.cumsum(steps).max(initial=0))


class _Bad(Exception):
    pass


def _no_constant(name: str) -> Any:
    raise _Bad(f"{name} is not a finite number (JSON has no NaN or Infinity)")


def _finite_float(text: str) -> float:
    v = float(text)
    if not math.isfinite(v):
        raise _Bad(f"{printable(text, 40)} overflows a float")
    return v


def _unique_object(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in pairs:
        if k in out:
            raise _Bad(f"key {quote(k)} appears twice in one object")
        out[k] = v
    return out


def parse_json(data: bytes | str, where: str, *, max_bytes: int = MAX_JSON_BYTES,
               max_depth: int = MAX_JSON_DEPTH) -> Any:
    """Strict JSON: UTF-8, at most ``max_bytes`` and ``max_depth`` levels (both checked before parsing),
    finite numbers only, no duplicate keys. ``where`` names the document in the one-line error."""
    if len(data) > max_bytes:
        raise InputError(f"{where}: {len(data):,} bytes of JSON, more than the {max_bytes:,} allowed")
    if isinstance(data, (bytes, bytearray, memoryview)):
        try:
            text = bytes(data).decode("utf-8")
        except UnicodeDecodeError as e:
            raise InputError(f"{where}: not UTF-8 JSON text (invalid byte at offset {e.start})") from None
    else:
        text = data
    depth = json_depth(text)
    if depth > max_depth:
        raise InputError(f"{where}: JSON nested {depth} levels deep, more than the {max_depth} allowed")
    try:
        return json.loads(text, parse_constant=_no_constant, parse_float=_finite_float,
                          object_pairs_hook=_unique_object)
    except _Bad as e:
        raise InputError(f"{where}: {e}") from None
    except json.JSONDecodeError as e:
        raise InputError(f"{where}: not valid JSON ({e.msg} at line {e.lineno} column {e.colno})") from None
    except (ValueError, RecursionError) as e:  # an integer literal beyond Python's digit limit
        raise InputError(f"{where}: not valid JSON ({printable(str(e).splitlines()[0] if str(e) else type(e).__name__, 80)})") from None


def read_json_file(path: str | os.PathLike, what: str, *, max_bytes: int = MAX_JSON_BYTES,
                   max_depth: int = MAX_JSON_DEPTH) -> Any:
    """A JSON file through :func:`read_regular_file` and :func:`parse_json`."""
    data = read_regular_file(path, what, max_bytes)
    return parse_json(data, f"{what} {quote(path)}", max_bytes=max_bytes, max_depth=max_depth)


# --- .npz archives -------------------------------------------------------------------------------
_EOCD = struct.Struct("<4s4H2LH")  # end of central directory record
_ZIP64_LOCATOR = b"PK\x06\x07"


def _zip_directory(raw: bytes, bad: Callable[[str], Exception]) -> None:
    """Check the end-of-central-directory record before :mod:`zipfile` reads the directory."""
    tail = raw[-(0xFFFF + _EOCD.size):]
    at = tail.rfind(b"PK\x05\x06")
    if at < 0 or len(tail) - at < _EOCD.size:
        raise bad("is not a .npz (zip) archive; truncated or not a policy")
    _, disk, cd_disk, n_here, n_total, cd_size, cd_offset, _ = _EOCD.unpack_from(tail, at)
    start = len(raw) - len(tail) + at
    if start >= 20 and raw[start - 20:start - 16] == _ZIP64_LOCATOR:
        raise bad("is a zip64 archive; a policy file is a small plain zip")
    if disk != 0 or cd_disk != 0 or n_here != n_total:
        raise bad("is a multi-disk zip archive; not a policy file")
    if n_total > MAX_NPZ_MEMBERS:
        raise bad(f"holds {n_total:,} members, more than the {MAX_NPZ_MEMBERS} a policy may have")
    if cd_size > MAX_ZIP_DIRECTORY_BYTES or cd_size + cd_offset > start:
        raise bad(f"has a zip directory of {cd_size:,} bytes that does not fit the archive")


def _npy_array(data: bytes, member: str, bad: Callable[[str], Exception]) -> np.ndarray:
    """An array from the bytes of one ``.npy`` member: header parsed and checked against the size first."""
    f = io.BytesIO(data)
    try:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(f, max_header_size=MAX_NPY_HEADER)
        elif version == (2, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(f, max_header_size=MAX_NPY_HEADER)
        else:
            raise bad(f"member {quote(member)}: .npy format version {version} is not supported")
    except (ValueError, SyntaxError, TypeError, EOFError) as e:
        raise bad(f"member {quote(member)}: not a valid .npy array ({printable(str(e).splitlines()[0] if str(e) else type(e).__name__, 80)})") from None
    if dtype.hasobject or dtype.fields is not None or dtype.subdtype is not None or dtype.kind not in _ARRAY_KINDS:
        raise bad(f"member {quote(member)}: dtype {printable(dtype.str)} is not plain numeric data "
                  "(policy files never hold objects)")
    if not isinstance(shape, tuple) or len(shape) > 8 or any(not isinstance(d, int) or d < 0 for d in shape):
        raise bad(f"member {quote(member)}: invalid shape {printable(shape, 60)}")
    count = math.prod(shape)
    offset = f.tell()
    if count * dtype.itemsize != len(data) - offset:
        raise bad(f"member {quote(member)}: its header says {shape} x {dtype.itemsize} bytes but it holds "
                  f"{len(data) - offset:,} bytes; truncated or corrupt")
    arr = np.frombuffer(data, dtype=dtype, count=count, offset=offset)
    return arr.reshape(shape[::-1]).T if fortran else arr.reshape(shape)


def read_npz(raw: bytes, bad: Callable[[str], Exception]) -> dict[str, np.ndarray]:
    """The arrays of an ``.npz`` archive, every limit checked before anything is decompressed.

    ``bad(msg)`` builds the exception (it names the file). Members must be ``<name>.npy`` files,
    stored or deflated, unencrypted, unique, of plain numeric dtype; their declared sizes bound what
    is decompressed (and zipfile's CRC check refuses a member that lies about its size).
    """
    _zip_directory(raw, bad)
    try:
        zf = zipfile.ZipFile(io.BytesIO(raw))
    except (zipfile.BadZipFile, OSError, ValueError, EOFError, struct.error, NotImplementedError) as e:
        raise bad(f"is not a valid zip archive ({printable(str(e) or type(e).__name__, 80)}); truncated or corrupt") from None
    with zf:
        infos = zf.infolist()
        names = [i.filename for i in infos]
        total = 0
        for info in infos:
            if not _MEMBER_NAME.fullmatch(info.filename):
                raise bad(f"member {quote(info.filename)} is not an array of a policy file (<name>.npy)")
            if names.count(info.filename) > 1:
                raise bad(f"member {quote(info.filename)} appears twice")
            if info.flag_bits & 0x1:
                raise bad(f"member {quote(info.filename)} is encrypted")
            if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
                raise bad(f"member {quote(info.filename)} uses zip compression method {info.compress_type} "
                          "(only stored or deflated)")
            total += info.file_size
            if info.file_size > MAX_NPZ_BYTES or total > MAX_NPZ_BYTES:
                raise bad(f"members decompress to more than {MAX_NPZ_BYTES:,} bytes "
                          f"({quote(info.filename)} alone to {info.file_size:,}); not a Kilobot policy")
        arrays: dict[str, np.ndarray] = {}
        for info in infos:
            try:
                data = zf.read(info)
            except (zipfile.BadZipFile, OSError, EOFError, ValueError, NotImplementedError, struct.error) as e:
                raise bad(f"member {quote(info.filename)} is corrupt or truncated "
                          f"({printable(str(e).splitlines()[0] if str(e) else type(e).__name__, 80)})") from None
            except Exception as e:  # zlib.error from a damaged deflate stream
                raise bad(f"member {quote(info.filename)} is corrupt ({type(e).__name__})") from None
            if len(data) != info.file_size:
                raise bad(f"member {quote(info.filename)} is truncated")
            arrays[info.filename[:-4]] = _npy_array(data, info.filename, bad)
    return arrays
