"""CRC-16/MCRF4XX, the CRC of a Kilobot message (our own implementation).

Parameters: polynomial 0x1021 reflected (0x8408), init 0xFFFF, input and output reflected, no final
xor; the same update as avr-libc's ``_crc_ccitt_update``. kilolib checks it over the first 10 bytes
of ``message_t`` (9 payload bytes and the type) and drops messages whose CRC does not match, so the
firmware computes it for every message it sends (``kf_crc16`` in ``firmware_templates/kf_runtime.h``,
the same bit loop as here).

>>> hex(crc16_mcrf4xx(bytes(range(1, 10)) + b"\\x00"))
'0xa718'
>>> hex(crc16_mcrf4xx(bytes(10)))
'0x9c87'
"""
from __future__ import annotations

import numpy as np

POLY_REFLECTED = 0x8408
INIT = 0xFFFF


def crc16_mcrf4xx(data: bytes | bytearray | memoryview, crc: int = INIT) -> int:
    """CRC of ``data`` (continuing from ``crc``).

    >>> crc16_mcrf4xx(b"123456789") == 0x6F91  # the catalogue check value of CRC-16/MCRF4XX
    True
    """
    for byte in bytes(data):
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ POLY_REFLECTED if crc & 1 else crc >> 1
    return crc


def crc16_rows(rows: np.ndarray) -> np.ndarray:
    """CRC of every row of a uint8 array (..., n) -> (...,) uint16, vectorised over rows.

    >>> crc16_rows(np.array([[1, 2, 3, 4, 5, 6, 7, 8, 9, 0], [0] * 10], np.uint8)).tolist()
    [42776, 40071]
    """
    rows = np.asarray(rows)
    assert rows.dtype == np.uint8, f"crc16_rows needs uint8 rows, got {rows.dtype}"
    crc = np.full(rows.shape[:-1], INIT, np.uint32)
    for i in range(rows.shape[-1]):
        crc ^= rows[..., i]
        for _ in range(8):
            crc = np.where(crc & 1, (crc >> 1) ^ POLY_REFLECTED, crc >> 1)
    return crc.astype(np.uint16)
