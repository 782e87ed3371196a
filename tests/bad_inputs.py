"""Hostile inputs for the hardening tests, the fuzzing suite and tests/soak/fuzz_all.py: crafted policy
files (with or without a valid hash), zip bombs, deep JSON, and a check that output is one clean line."""
from __future__ import annotations

import io
import json
import struct
import zipfile
from typing import Any, Mapping

import numpy as np

from tests.fixtures import init_policy
from kiloforge.artifact import META, artifact_bytes, npz_bytes
from sim.config import preset

KILOBOT = preset("kilobot")


def small_policy(seed: int = 3, world=KILOBOT, t_prev: int = 2, hidden=(6,), notes: str = "hardening test"):
    return init_policy(world, t_prev, hidden, "elu", seed=seed, out_scale=0.3,
                       provenance={"trainer": "test", "notes": notes})


def parts(policy) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """A policy's arrays and meta (without policy_hash), as a crafted file starts from."""
    return {k: np.array(v) for k, v in policy.arrays().items()}, policy.meta()


def crafted(arrays: Mapping[str, np.ndarray], meta: Mapping[str, Any], *, hashed: bool = True) -> bytes:
    """A policy file with exactly this meta: with the hash of its (possibly invalid) contents, or without one."""
    if hashed:
        return artifact_bytes(dict(arrays), dict(meta))
    members = dict(arrays)
    members[META] = np.frombuffer(json.dumps(dict(meta)).encode("utf-8"), np.uint8)
    return npz_bytes(members)


def raw_meta_file(arrays: Mapping[str, np.ndarray], meta_text: bytes) -> bytes:
    """A policy file whose meta member holds these bytes (not necessarily JSON)."""
    members = dict(arrays)
    members[META] = np.frombuffer(meta_text, np.uint8)
    return npz_bytes(members)


def nested_json(depth: int, leaf: str = "1") -> str:
    """``[[[ ... ]]]`` nested ``depth`` levels deep."""
    return "[" * depth + leaf + "]" * depth


def _patch_sizes(raw: bytes, member: str, size: int) -> bytes:
    """Set a member's uncompressed size in its local header and its central directory entry."""
    b = bytearray(raw)
    name = member.encode()
    # (signature, offset of the name length, of the name, of the uncompressed size)
    for sig, len_at, name_at, size_at in ((b"PK\x03\x04", 26, 30, 22), (b"PK\x01\x02", 28, 46, 24)):
        at = b.find(sig)
        while at >= 0:
            n = struct.unpack_from("<H", b, at + len_at)[0]
            if bytes(b[at + name_at:at + name_at + n]) == name:
                struct.pack_into("<I", b, at + size_at, size)
            at = b.find(sig, at + 4)
    return bytes(b)


def zip_bomb(actual_mib: int = 100, declared: int | None = None) -> bytes:
    """An .npz whose member ``w0.npy`` inflates to ``actual_mib`` MiB (a valid .npy of zeros), about 1000:1;
    ``declared``: the uncompressed size its headers claim instead (a member that lies about its size)."""
    n = actual_mib * (1 << 20) // 4
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f4", "fortran_order": False, "shape": (n,)})
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        info = zipfile.ZipInfo("w0.npy", date_time=(1980, 1, 1, 0, 0, 0))
        info.compress_type = zipfile.ZIP_DEFLATED
        with zf.open(info, "w", force_zip64=False) as f:
            f.write(header.getvalue())
            chunk = bytes(1 << 20)
            for _ in range(actual_mib):
                f.write(chunk)
        zf.writestr(zipfile.ZipInfo("meta.npy", date_time=(1980, 1, 1, 0, 0, 0)), _npy(np.frombuffer(b"{}", np.uint8)))
    raw = buf.getvalue()
    return raw if declared is None else _patch_sizes(raw, "w0.npy", declared)


def _npy(a: np.ndarray) -> bytes:
    b = io.BytesIO()
    np.lib.format.write_array(b, a, allow_pickle=False)
    return b.getvalue()


def many_members(n: int = 5000) -> bytes:
    """A zip of ``n`` tiny members (a directory far larger than any policy's)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for i in range(n):
            zf.writestr(f"a{i}.npy", b"")
    return buf.getvalue()


def huge_shape_member() -> bytes:
    """A 1-KB .npz whose ``w0.npy`` header claims 10**12 float32 values."""
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f4", "fortran_order": False, "shape": (10**12,)})
    return npz_bytes_raw({"w0.npy": header.getvalue() + bytes(64), "meta.npy": _npy(np.frombuffer(b"{}", np.uint8))})


def npz_bytes_raw(members: Mapping[str, bytes], compress: int = zipfile.ZIP_STORED) -> bytes:
    """A zip with exactly these member bytes."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=compress) as zf:
        for name, data in members.items():
            zf.writestr(zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0)), data)
    return buf.getvalue()


def assert_one_clean_line(err: str) -> str:
    """stderr is one line, without a traceback and without raw control characters; returns it."""
    lines = [l for l in err.splitlines() if l.strip()]
    assert len(lines) == 1, f"expected one line, got {err!r}"
    assert "Traceback" not in err, err
    assert all(c.isprintable() for c in lines[0]), f"raw control characters in {lines[0]!r}"
    return lines[0]
