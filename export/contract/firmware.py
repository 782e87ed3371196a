"""Constants of the generated Kilobot firmware that the renderer, the emulator and the host harness share.

The message a robot sends (``message_t``, 12 bytes, packed)::

    data[0]     KF_MSG_VERSION (MSG_VERSION)          payload layout version; other values are dropped
    data[1..2]  kilo_uid, little-endian
    data[3]     role | (sensing << 1)                 role 1 = the emitter; sensing = "I heard the target
                                                      during the last control period"
    data[4..5]  the emitter's held ambient-light reading (0..1023, LIGHT_NONE before its first), little-endian,
                only in worlds whose observation reads it (the ``object_light`` feature); else 0
    data[6..8]  0
    type        KF_MSG_TYPE (default DEFAULT_MSG_TYPE) a user type: < 0x80 and != 1 (1 is the overhead
                                                      controller's GPS message)
    crc         CRC-16/MCRF4XX over the first 10 bytes, little-endian (export.contract.crc)

The LED (``set_color`` byte, kilolib's 2 bits per channel: red bits 0-1, green 2-3, blue 4-5):
the emitter blue; a searcher that heard the target this period green; else one whose neighbour table
holds a searcher that senses the target yellow; else off.

Per-tick outputs of the firmware (what the host harness writes and the emulator produces), one
record of :data:`TICK_RECORD_BYTES` bytes per robot and kilo_tick::

    [0] left duty   [1] right duty   (the last set_motors values)
    [2] spinup      1 when spinup_motors() was called during this tick's loop()
    [3] LED         the last set_color value
    [4..15]         the 12 bytes of the message kilo_message_tx() returns after this tick's loop()

Per control step (at ticks k * period_ticks, k >= 1: the first period only listens; searchers
only, zeros for emitters): ``[q_left, q_right, obs[0..obs_dim-1]]``, the uint8 motor commands and
the int8 observation (as bytes).
"""
from __future__ import annotations

import numpy as np

MSG_VERSION = 1  #: data[0] of every message of ours
DEFAULT_MSG_TYPE = 0x2A  #: message type of ours unless the user picks another
MSG_DATA_BYTES = 9  #: kilolib's message_t payload, data[0..8]
MSG_USED_BYTES = 4  #: data[0..3] carry version, uid and info; data[4..8] are 0 (but MSG_LIGHT_BYTE's two)
MSG_INFO_BYTE = 3  #: data[3]: role | sensing << 1
MSG_LIGHT_BYTE = 4  #: data[4..5]: the emitter's held light reading, little-endian (worlds with ``object_light``)
LIGHT_NONE = 0xFFFF  #: data[4..5] of an emitter that has no reading yet; receivers keep only readings <= 1023
MSG_TYPE_BYTE = MSG_DATA_BYTES  #: the type follows the payload
MSG_CRC_BYTES = MSG_DATA_BYTES + 1  #: the CRC covers the payload and the type
MSG_BYTES = MSG_CRC_BYTES + 2  #: sizeof(message_t): payload, type, crc16 (packed)
RXQ_CAPACITY = 8  #: messages buffered between the rx ISR and loop(); a message arriving when full is dropped
#: ``ready`` of the per-robot state once setup() has finished; until then the rx and tx callbacks do
#: nothing (kilolib calls them before setup() too). 16 bits with two non-zero bytes: a garbage state
#: (Kilombo's is malloc'd) matches it once in 65,536, and writing it byte by byte over 0 (or 0 over
#: it) never passes through it.
STATE_READY = 0x4B46

ROLE_BIT = 0x01  #: data[3] bit 0: sender is the emitter (the task's transmitting robot)
SENSING_BIT = 0x02  #: data[3] bit 1: sender heard the target during its last control period


def rgb(r: int, g: int, b: int) -> int:
    """kilolib's colour byte: 2 bits per channel (red bits 0-1, green 2-3, blue 4-5).

    >>> rgb(0, 0, 1), rgb(1, 1, 0), rgb(3, 3, 3)
    (16, 5, 63)
    """
    return (r & 3) | ((g & 3) << 2) | ((b & 3) << 4)


LED_OFF = (0, 0, 0)
LED_EMITTER = (0, 0, 1)  #: blue: this robot is the emitter
LED_SENSING = (0, 1, 0)  #: green: heard the target during the last control period
LED_NBR_SENSING = (1, 1, 0)  #: yellow: a neighbour heard this period senses the target

TICK_RECORD_BYTES = 4 + MSG_BYTES  #: per robot and tick: left, right, spinup, led, message

#: One received message, as the event stream of the host harness and the emulator carry it.
#: ``robot`` is the receiver (0..R-1), ``tick`` the global kilo_tick during which it arrives (it is
#: delivered to the rx callback after that tick's loop()), then what the message says and the
#: distance estimate_distance() returns for it. ``type``/``version`` let a stream inject foreign or
#: malformed messages. ``role`` and ``flag`` are 0/1; ``light`` is data[4..5] (0 in messages that carry none).
EVENT_DTYPE = np.dtype([("robot", "<u4"), ("tick", "<u4"), ("uid", "<u2"), ("role", "u1"),
                        ("flag", "u1"), ("type", "u1"), ("version", "u1"), ("dist", "u1"), ("light", "<u2")])

#: Calibration values (kilo_straight_left, kilo_straight_right, kilo_turn_left, kilo_turn_right)
#: used when a caller gives none: in the range of duties a calibrated Kilobot ends up with.
DEFAULT_CALIB = (70, 70, 72, 72)


def check_msg_type(msg_type: int) -> int:
    """Validate a message type of ours: a user type (< 0x80) other than 1 (the GPS message).

    >>> check_msg_type(0x2A)
    42
    >>> check_msg_type(1)
    Traceback (most recent call last):
    ...
    ValueError: message type 1 is the overhead controller's GPS message; choose 0 or 2..127
    """
    t = int(msg_type)
    if t == 1:
        raise ValueError("message type 1 is the overhead controller's GPS message; choose 0 or 2..127")
    if not 0 <= t < 0x80:
        raise ValueError(f"message type {t} is not a user type (kilolib consumes types >= 0x80); choose 0 or 2..127")
    return t
