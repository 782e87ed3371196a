"""CRC-16/MCRF4XX of Kilobot messages: test vectors, the vectorised version, message bytes."""
from __future__ import annotations

import numpy as np

from export.contract.crc import crc16_mcrf4xx, crc16_rows
from export.verify.emulator import message_bytes


def test_platform_test_vectors():
    """Data 01..09 with type 0 gives 0xA718; ten zero bytes give 0x9C87 (platform notes)."""
    assert crc16_mcrf4xx(bytes(range(1, 10)) + b"\x00") == 0xA718
    assert crc16_mcrf4xx(bytes(10)) == 0x9C87


def test_catalogue_check_value_and_empty_input():
    """The catalogue check value of CRC-16/MCRF4XX is 0x6F91; no data leaves the init value."""
    assert crc16_mcrf4xx(b"123456789") == 0x6F91
    assert crc16_mcrf4xx(b"") == 0xFFFF


def test_incremental_update():
    """Feeding the data in two pieces gives the same CRC as in one."""
    data = bytes(range(10, 30))
    assert crc16_mcrf4xx(data[7:], crc16_mcrf4xx(data[:7])) == crc16_mcrf4xx(data)


def test_rows_match_scalar():
    """The vectorised CRC equals the scalar one on random rows."""
    rng = np.random.default_rng(np.random.SeedSequence(3))
    rows = rng.integers(0, 256, size=(200, 10)).astype(np.uint8)
    want = [crc16_mcrf4xx(r.tobytes()) for r in rows]
    np.testing.assert_array_equal(crc16_rows(rows), np.array(want, np.uint16))


def test_message_bytes_layout_and_crc():
    """message_bytes lays out version, uid LE, info, zeros, type and a valid little-endian CRC."""
    uids = np.array([1, 0xBEEF, 0xFFFF], np.uint16)
    m = message_bytes(uids, np.array([0, 2, 3]), 0x2A)
    assert m.shape == (3, 12)
    np.testing.assert_array_equal(m[:, 0], 1)
    np.testing.assert_array_equal(m[:, 1] | (m[:, 2].astype(np.uint16) << 8), uids)
    np.testing.assert_array_equal(m[:, 3], [0, 2, 3])
    np.testing.assert_array_equal(m[:, 4:9], 0)
    np.testing.assert_array_equal(m[:, 9], 0x2A)
    for row in m:
        assert int(row[10]) | (int(row[11]) << 8) == crc16_mcrf4xx(row[:10].tobytes())
