"""Sync box wire protocol: message encoding, COBS framing and CRC-16/CCITT-FALSE.

The protocol is specified in docs/sync-protocol.md; this module is its reference
implementation (the host driver and the simulated box both use it). A frame on the wire is
``COBS(type || body || crc16_le) || 0x00``; integers are little-endian.
"""
from __future__ import annotations

import enum
import struct
from dataclasses import dataclass

__all__ = [
    "MsgType", "NakCode", "Message", "crc16_ccitt_false", "cobs_encode", "cobs_decode",
    "encode_message", "decode_frame", "checked_body", "FrameSplitter", "DecodeError", "PROTOCOL_VERSION",
    "MAX_FRAME_LEN",
]

PROTOCOL_VERSION = (1, 0)
MAX_FRAME_LEN = 256  # encoded bytes between delimiters; longer runs are garbage


class MsgType(enum.IntEnum):
    # host -> box
    GET_VERSION = 0x01
    SET_RATE = 0x02
    SET_EXPOSURE = 0x03
    START = 0x04
    STOP = 0x05
    TIME_QUERY = 0x06
    # box -> host
    ACK = 0x81
    NAK = 0x82
    VERSION = 0x83
    TIME_REPLY = 0x84
    PULSE = 0x85
    BOOT = 0x86


class NakCode(enum.IntEnum):
    BAD_CRC = 1
    UNKNOWN_TYPE = 2
    BAD_LENGTH = 3
    OUT_OF_RANGE = 4
    BUSY = 5
    NOT_CONFIGURED = 6


# body layouts (struct format after the type byte); VERSION has a trailing UTF-8 name
_LAYOUT: dict[MsgType, tuple[str, tuple[str, ...]]] = {
    MsgType.GET_VERSION: ("<H", ("seq",)),
    MsgType.SET_RATE: ("<HI", ("seq", "rate_mhz")),
    MsgType.SET_EXPOSURE: ("<HII", ("seq", "width_us", "delay_us")),
    MsgType.START: ("<H", ("seq",)),
    MsgType.STOP: ("<H", ("seq",)),
    MsgType.TIME_QUERY: ("<H", ("seq",)),
    MsgType.ACK: ("<HB", ("seq", "cmd")),
    MsgType.NAK: ("<HBB", ("seq", "cmd", "code")),
    MsgType.VERSION: ("<HBBI", ("seq", "major", "minor", "tick_hz")),
    MsgType.TIME_REPLY: ("<HQ", ("seq", "ticks")),
    MsgType.PULSE: ("<IQ", ("index", "ticks")),
    MsgType.BOOT: ("<BBBI", ("reason", "major", "minor", "tick_hz")),
}


class DecodeError(ValueError):
    """A frame failed COBS, CRC, type or length checks."""


@dataclass(frozen=True, kw_only=True)
class Message:
    """One protocol message: its type and named integer fields (plus ``name`` for VERSION)."""

    type: MsgType
    fields: dict
    name: str = ""

    def __getattr__(self, item):
        f = self.__dict__.get("fields", {})
        if item in f:
            return f[item]
        raise AttributeError(item)

    @classmethod
    def make(cls, type: MsgType, name: str = "", **fields) -> "Message":
        fmt, names = _LAYOUT[MsgType(type)]
        if set(fields) != set(names):
            raise ValueError(f"{MsgType(type).name} needs fields {names}, got {sorted(fields)}")
        return cls(type=MsgType(type), fields=dict(fields), name=name)


def crc16_ccitt_false(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, xorout 0.

    Check value: ``crc16_ccitt_false(b"123456789") == 0x29B1``.
    """
    for b in data:
        crc ^= b << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


def cobs_encode(data: bytes) -> bytes:
    """Consistent Overhead Byte Stuffing: output contains no 0x00 (delimiter not appended)."""
    out = bytearray([0])
    code_i, code = 0, 1
    for b in data:
        if b == 0:
            out[code_i] = code
            code_i, code = len(out), 1
            out.append(0)
        else:
            out.append(b)
            code += 1
            if code == 0xFF:
                out[code_i] = code
                code_i, code = len(out), 1
                out.append(0)
    out[code_i] = code
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Inverse of ``cobs_encode``; raises ``DecodeError`` on malformed input."""
    out = bytearray()
    i, n = 0, len(data)
    while i < n:
        code = data[i]
        if code == 0:
            raise DecodeError("zero byte inside COBS frame")
        if i + code > n:
            raise DecodeError(f"COBS code {code} at {i} overruns frame of {n} bytes")
        out += data[i + 1:i + code]
        i += code
        if code < 0xFF and i < n:
            out.append(0)
    return bytes(out)


def encode_message(msg: Message) -> bytes:
    """Wire bytes of one message, including the trailing 0x00 delimiter."""
    fmt, names = _LAYOUT[msg.type]
    body = bytes([int(msg.type)]) + struct.pack(fmt, *(int(msg.fields[k]) for k in names))
    if msg.type == MsgType.VERSION:
        body += msg.name.encode("utf-8")[:64]
    body += struct.pack("<H", crc16_ccitt_false(body))
    return cobs_encode(body) + b"\x00"


def checked_body(frame: bytes) -> bytes:
    """``type || body`` of a frame that passes COBS and CRC (type and length unchecked);
    raises ``DecodeError``. The box uses it to NAK well-formed frames it cannot parse."""
    raw = cobs_decode(frame)
    if len(raw) < 3:
        raise DecodeError(f"frame of {len(raw)} bytes is too short")
    body, crc = raw[:-2], struct.unpack("<H", raw[-2:])[0]
    if crc16_ccitt_false(body) != crc:
        raise DecodeError("CRC mismatch")
    return body


def decode_frame(frame: bytes) -> Message:
    """Decode the bytes between two delimiters; raises ``DecodeError``."""
    body = checked_body(frame)
    try:
        t = MsgType(body[0])
    except ValueError:
        raise DecodeError(f"unknown message type 0x{body[0]:02x}") from None
    fmt, names = _LAYOUT[t]
    size = struct.calcsize(fmt)
    payload = body[1:]
    if (len(payload) != size) if t != MsgType.VERSION else (len(payload) < size):
        raise DecodeError(f"{t.name} body of {len(payload)} bytes, expected {size}")
    values = struct.unpack(fmt, payload[:size])
    name = payload[size:].decode("utf-8", "replace") if t == MsgType.VERSION else ""
    return Message(type=t, fields=dict(zip(names, values)), name=name)


class FrameSplitter:
    """Incremental splitter of a byte stream into delimiter-terminated frames.

    Keeps a partial frame across ``feed`` calls; drops runs longer than ``MAX_FRAME_LEN``
    (counted in ``overruns``) so a stream of garbage cannot grow memory.
    """

    def __init__(self, max_len: int = MAX_FRAME_LEN):
        self._buf = bytearray()
        self._max = max_len
        self._discarding = False
        self.overruns = 0

    def feed(self, data: bytes) -> list[bytes]:
        frames = []
        start = 0
        for i in _zero_positions(data):
            chunk = data[start:i]
            if self._discarding:
                self._discarding = False
            elif len(self._buf) + len(chunk) <= self._max:
                self._buf += chunk
                if self._buf:
                    frames.append(bytes(self._buf))
            else:
                self.overruns += 1
            self._buf.clear()
            start = i + 1
        rest = data[start:]
        if not self._discarding:
            if len(self._buf) + len(rest) > self._max:
                self._buf.clear()
                self._discarding = True
                self.overruns += 1
            else:
                self._buf += rest
        return frames


def _zero_positions(data: bytes):
    i = data.find(0)
    while i >= 0:
        yield i
        i = data.find(0, i + 1)
