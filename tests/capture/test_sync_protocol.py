"""Wire format of docs/sync-protocol.md: CRC, COBS, messages, frame splitting."""
import re
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from capture.sync_protocol import (DecodeError, FrameSplitter, Message, MsgType,
                                   checked_body, cobs_decode, cobs_encode, crc16_ccitt_false,
                                   decode_frame, encode_message)

DOC = Path(__file__).resolve().parents[2] / "docs" / "sync-protocol.md"
_ROW = re.compile(r"^\| `(?P<msg>[A-Z_]+(?: [^`]*)?)` \| `(?P<pre>[0-9A-F ]+)` \| "
                  r"`(?P<wire>[0-9A-F ]+)` \|$")


def test_crc_check_value():
    assert crc16_ccitt_false(b"123456789") == 0x29B1


def test_cobs_spec_example():
    assert cobs_encode(bytes([0x11, 0x22, 0x00, 0x33])) == bytes([0x03, 0x11, 0x22, 0x02, 0x33])


def test_doc_example_bytes():
    wire = encode_message(Message.make(MsgType.TIME_QUERY, seq=7))
    assert wire == bytes.fromhex("03 06 07 03 AB E7 00")


def _doc_rows():
    rows = [m.groupdict() for m in map(_ROW.match, DOC.read_text().splitlines()) if m]
    return rows


def test_doc_has_a_vector_for_every_message_type():
    names = {r["msg"].split()[0] for r in _doc_rows()}
    assert names == {t.name for t in MsgType}


@pytest.mark.parametrize("row", _doc_rows(), ids=lambda r: r["msg"].split()[0])
def test_every_doc_vector_matches_the_encoder(row):
    name, *fields = re.findall(r'[A-Z_]+|\w+=(?:"[^"]*"|\d+)', row["msg"])
    kw = {k: v for k, v in (f.split("=", 1) for f in fields)}
    text = kw.pop("name", '""').strip('"')
    msg = Message.make(MsgType[name], name=text, **{k: int(v) for k, v in kw.items()})
    wire = encode_message(msg)
    assert wire == bytes.fromhex(row["wire"])
    pre = bytes.fromhex(row["pre"])
    assert checked_body(wire[:-1]) == pre[:-2]
    assert struct.unpack("<H", pre[-2:])[0] == crc16_ccitt_false(pre[:-2])
    back = decode_frame(wire[:-1])
    assert back.fields == msg.fields and back.name == text


@given(st.binary(max_size=700))
@settings(max_examples=200, deadline=None)
def test_cobs_roundtrip_no_zeros(data):
    enc = cobs_encode(data)
    assert 0 not in enc
    assert cobs_decode(enc) == data


@pytest.mark.parametrize("msg", [
    Message.make(MsgType.SET_RATE, seq=65535, rate_mhz=120_000),
    Message.make(MsgType.SET_EXPOSURE, seq=1, width_us=500, delay_us=10),
    Message.make(MsgType.PULSE, index=2**32 - 1, ticks=2**64 - 1),
    Message.make(MsgType.TIME_REPLY, seq=0, ticks=0),
    Message.make(MsgType.NAK, seq=3, cmd=2, code=5),
    Message.make(MsgType.VERSION, seq=9, major=1, minor=0, tick_hz=10**6, name="box é"),
    Message.make(MsgType.BOOT, reason=1, major=1, minor=0, tick_hz=10**6),
])
def test_message_roundtrip(msg):
    wire = encode_message(msg)
    assert wire[-1] == 0 and 0 not in wire[:-1]
    back = decode_frame(wire[:-1])
    assert back.type == msg.type and back.fields == msg.fields and back.name == msg.name


def test_every_single_bit_flip_is_rejected():
    wire = encode_message(Message.make(MsgType.PULSE, index=12345, ticks=987654321))[:-1]
    for i in range(len(wire)):
        for bit in range(8):
            bad = bytearray(wire)
            bad[i] ^= 1 << bit
            if 0 in bad:
                continue  # would be split by the delimiter, not delivered as one frame
            with pytest.raises(DecodeError):
                decode_frame(bytes(bad))


def test_wrong_field_set_raises():
    with pytest.raises(ValueError, match="rate_mhz"):
        Message.make(MsgType.SET_RATE, seq=1)


def test_splitter_partial_frames_and_garbage():
    rng = np.random.default_rng(0)
    msgs = [Message.make(MsgType.PULSE, index=i, ticks=1000 * i) for i in range(50)]
    stream = b"".join(encode_message(m) for m in msgs)
    stream = bytes(rng.integers(1, 256, 1000, dtype=np.uint8)) + b"\x00" + stream
    sp = FrameSplitter()
    got = []
    pos = 0
    while pos < len(stream):
        n = int(rng.integers(1, 9))
        for fr in sp.feed(stream[pos:pos + n]):
            try:
                got.append(decode_frame(fr))
            except DecodeError:
                pass
        pos += n
    assert [m.index for m in got] == list(range(50))
    assert sp.overruns == 1  # the 1000-byte run was discarded, not buffered


@given(st.lists(st.tuples(st.integers(0, 2**32 - 1), st.integers(0, 2**64 - 1)), max_size=30),
       st.lists(st.integers(1, 40), min_size=1, max_size=20))
@settings(max_examples=100, deadline=None)
def test_property_any_chunking_yields_the_messages(pulses, cuts):
    wire = b"".join(encode_message(Message.make(MsgType.PULSE, index=i, ticks=t))
                    for i, t in pulses)
    sp, got, pos, k = FrameSplitter(), [], 0, 0
    while pos < len(wire):
        n = cuts[k % len(cuts)]
        got += [decode_frame(f) for f in sp.feed(wire[pos:pos + n])]
        pos, k = pos + n, k + 1
    assert [(m.index, m.ticks) for m in got] == pulses
