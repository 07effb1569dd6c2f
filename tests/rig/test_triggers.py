from __future__ import annotations

import re
import socket
import threading
import time

import can
import pytest
import serial

from rig.triggers import (
    CAN_ERR_BUSOFF,
    DEFAULT_SERIAL_PATTERN,
    CanTrigger,
    SerialTrigger,
    SoftwareTrigger,
    TriggerEvent,
    TriggerFilter,
    decode_can_trigger,
    encode_can_trigger,
    format_trigger_line,
    parse_trigger_line,
)


def _drain(src, n: int, timeout: float = 5.0) -> list[TriggerEvent]:
    out, deadline = [], time.monotonic() + timeout
    while len(out) < n and time.monotonic() < deadline:
        ev = src.get(timeout=0.05)
        if ev is not None:
            out.append(ev)
    return out


def _wait(cond, timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.01)
    return False


def test_codecs_round_trip_and_reject_garbage():
    pat = re.compile(DEFAULT_SERIAL_PATTERN)
    assert parse_trigger_line(format_trigger_line(17, -42).rstrip(b"\n"), pat) == {"seq": 17, "encoder": -42}
    assert parse_trigger_line(b"TRIG,17,-42\r", pat) == {"seq": 17, "encoder": -42}
    for junk in (b"TRIG,x,1", b"\xff\xfeTRIG,1,2", b"", b"HELLO"):
        assert parse_trigger_line(junk, pat) is None
    assert decode_can_trigger(encode_can_trigger(70000, -5)) == {"seq": 70000, "encoder": -5}
    assert decode_can_trigger(b"\x01\x02") is None


def test_filter_storm_counts_every_event_deterministically():
    """1 kHz for 2 s (2000 triggers, 1 ms apart) with a 50 ms minimum interval, a duplicated frame and a gap."""
    f = TriggerFilter(debounce_ns=5_000_000, min_interval_ns=50_000_000)
    seqs = [s for s in range(1, 2001) if s not in (500, 501, 502)]
    verdicts = [f.check(TriggerEvent(s, "can", s * 1_000_000)) for s in seqs]
    verdicts.append(f.check(TriggerEvent(2000, "can", 2_000_000_100)))  # the controller repeated its last frame
    assert f.received == 1998 and f.duplicates == 1 and f.missed == 3
    assert f.accepted == 40  # t = 1, 51, 101, ... ms: one per 50 ms, exactly
    assert f.accepted + f.too_soon + f.duplicates == f.received
    assert [v.missed for v in verdicts if v.missed] == [3]


def test_filter_debounces_seqless_contact_bounce():
    f = TriggerFilter(debounce_ns=5_000_000)
    accepted = [f.check(TriggerEvent(None, "io", t)).accept for t in (0, 1_000_000, 3_000_000, 20_000_000, 21_000_000)]
    assert accepted == [True, False, False, True, False] and f.duplicates == 3


def test_serial_loop_survives_garbage_and_split_lines():
    port = serial.serial_for_url("loop://", timeout=0.05)
    src = SerialTrigger("loop://", open_port=lambda: port).start()
    try:
        port.write(b"\x00\xff\xfegarbage\nTRIG,1,10")
        time.sleep(0.05)
        port.write(b"0\nTRIG,2,2")  # seq 1's line completes here; seq 2 split across writes
        time.sleep(0.05)
        port.write(b"00\nTRIG,zz,1\n" + b"#" * 1000 + b"\nTRIG,3,300\n")
        events = _drain(src, 3)
    finally:
        src.stop()
    assert [(e.seq, e.payload["encoder"]) for e in events] == [(1, 100), (2, 200), (3, 300)]
    assert src.stats["garbage"] == 3  # the binary junk, the bad seq, the over-long line


def test_an_over_long_line_counts_once_however_it_arrives_and_its_tail_is_never_a_trigger():
    """How the reader's reads cut the stream must not change what it counts (a loaded host reads smaller pieces)."""
    counts = []
    for pieces in ([b"#" * 300 + b"TRIG,9,900\nTRIG,3,300\n"], [b"#" * 200, b"#" * 100 + b"TRIG,9,9", b"00\nTRIG,3,300\n"]):
        src = SerialTrigger("loop://", open_port=lambda: None)
        for piece in pieces:
            src._feed(piece)
        events = []
        while (ev := src.get(timeout=0.01)) is not None:
            events.append(ev)
        assert [(e.seq, e.payload["encoder"]) for e in events] == [(3, 300)]
        counts.append(src.stats["garbage"])
    assert counts == [1, 1]


class _LinePlc:
    """A photo-eye controller on TCP that can drop off the network and come back on the same port."""

    def __init__(self):
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]

    def serve(self, lines: list[bytes]) -> None:
        conn, _ = self.sock.accept()
        time.sleep(0.2)  # pyserial discards whatever arrived before its open() returned; lines come later on a real line
        for line in lines:
            conn.sendall(line)
            time.sleep(0.01)
        time.sleep(0.1)
        conn.close()

    def vanish(self) -> None:
        self.sock.close()

    def come_back(self) -> None:
        self.sock = socket.create_server(("127.0.0.1", self.port))


def test_serial_socket_port_vanishes_and_returns():
    plc = _LinePlc()
    src = SerialTrigger(f"socket://127.0.0.1:{plc.port}", reconnect_s=0.05).start()
    try:
        plc.serve([format_trigger_line(s, s * 10) for s in (1, 2, 3)] + [b"TRIG,4,4"])  # seq 4 is cut off mid-line
        first = _drain(src, 3)
        plc.vanish()
        assert _wait(lambda: src.stats["reconnects"] >= 1)
        time.sleep(0.2)  # refused connections meanwhile: the reader keeps retrying
        plc.come_back()
        threading.Thread(target=plc.serve, args=([format_trigger_line(s, 0) for s in (6, 7)],), daemon=True).start()
        second = _drain(src, 2)
    finally:
        src.stop()
        plc.vanish()
    assert [e.seq for e in first + second] == [1, 2, 3, 6, 7]
    f = TriggerFilter()
    for e in first + second:
        f.check(e)
    assert f.missed == 2  # seq 4 (cut off by the disconnect) and 5 (sent while away) are reported, not lost silently


def test_can_bus_off_and_closed_bus_are_recovered():
    channel = f"test-busoff-{time.monotonic_ns()}"
    opened = []

    def factory():
        bus = can.Bus(interface="virtual", channel=channel)
        opened.append(bus)
        return bus

    src = CanTrigger(arbitration_id=0x181, bus_factory=factory, reconnect_s=0.05).start()
    plc = can.Bus(interface="virtual", channel=channel)
    try:
        assert _wait(lambda: len(opened) == 1)
        send = lambda seq: plc.send(can.Message(arbitration_id=0x181, data=encode_can_trigger(seq, seq * 3), is_extended_id=False))  # noqa: E731
        send(1)
        plc.send(can.Message(arbitration_id=0x7FF, data=b"\x00"))  # other traffic: ignored
        plc.send(can.Message(arbitration_id=0x181, data=b"\x01"))  # short payload: garbage
        send(2)
        assert [e.seq for e in _drain(src, 2)] == [1, 2]
        plc.send(can.Message(arbitration_id=CAN_ERR_BUSOFF, is_error_frame=True, data=bytes(8)))
        assert _wait(lambda: len(opened) == 2)  # reopened after bus-off
        send(4)
        assert [e.seq for e in _drain(src, 1)] == [4]
        opened[-1].shutdown()  # the interface goes away under the reader: recv raises CanOperationError
        assert _wait(lambda: len(opened) == 3)
        send(5)
        after = _drain(src, 1)
    finally:
        src.stop()
        plc.shutdown()
    assert [e.seq for e in after] == [5] and after[0].payload == {"encoder": 15}
    assert src.stats["bus_off"] == 1 and src.stats["bus_errors"] == 2 and src.stats["reconnects"] == 2 and src.stats["garbage"] == 1


def test_software_trigger_numbers_its_events():
    src = SoftwareTrigger(clock=iter(range(100, 200)).__next__)
    a, b = src.fire({"button": "kiosk"}), src.fire()
    assert (a.seq, b.seq, a.timestamp_ns, b.timestamp_ns) == (1, 2, 100, 101) and a.payload == {"button": "kiosk"}
    assert src.get(0) == a and src.get(0) == b and src.get(0) is None


def test_serial_pattern_without_seq_is_refused():
    with pytest.raises(ValueError, match="named group 'seq'"):
        SerialTrigger("loop://", pattern=r"^GO$")
