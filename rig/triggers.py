"""Triggers: one event type from a photo-eye on a serial line, a PLC on CAN, or a software button.

Every source runs a reader thread that survives what the factory floor does to it (garbage bytes,
split lines, a port that vanishes and returns, CAN error frames and bus-off) and puts
`TriggerEvent`s on a queue. `TriggerFilter` then decides, from the events' own timestamps and
sequence numbers (so the decision is reproducible), which ones become captures: duplicates within
the debounce window and triggers closer than the minimum interval are dropped and counted, and
gaps in the sequence are counted as missed triggers.
"""

from __future__ import annotations

import queue
import re
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

DEFAULT_SERIAL_PATTERN = r"^TRIG,(?P<seq>\d+),(?P<encoder>-?\d+)$"
DEFAULT_CAN_FORMAT = "<Ii"  # uint32 seq, int32 encoder count, little-endian
CAN_ERR_BUSOFF = 0x040  # SocketCAN error class bit (linux/can/error.h) carried in an error frame's id

Clock = Callable[[], int]


@dataclass(frozen=True)
class TriggerEvent:
    """`seq` from the controller (None for sources without one), `timestamp_ns` host monotonic time of arrival."""

    seq: int | None
    source: str
    timestamp_ns: int
    payload: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"seq": self.seq, "source": self.source, "timestamp_ns": self.timestamp_ns, "payload": dict(self.payload)}


# ---- pure codecs ---------------------------------------------------------------------------------


def parse_trigger_line(line: bytes, pattern: re.Pattern) -> dict | None:
    """One line (without its newline) -> {"seq": int, other named groups (ints where numeric)}, or None if it is not a trigger."""
    try:
        text = line.decode("ascii").strip()
    except UnicodeDecodeError:
        return None
    m = pattern.match(text)
    if m is None:
        return None
    out = {k: (int(v) if v is not None and re.fullmatch(r"-?\d+", v) else v) for k, v in m.groupdict().items()}
    return out if isinstance(out.get("seq"), int) else None


def format_trigger_line(seq: int, encoder: int) -> bytes:
    """The default serial protocol's line for a trigger (what a photo-eye controller sends)."""
    return f"TRIG,{seq},{encoder}\n".encode()


def decode_can_trigger(data: bytes, fmt: str = DEFAULT_CAN_FORMAT) -> dict | None:
    """CAN payload -> {"seq", "encoder"} per `fmt` (struct format, seq first), or None if it does not fit."""
    try:
        values = struct.unpack_from(fmt, bytes(data))
    except struct.error:
        return None
    out = {"seq": int(values[0])}
    if len(values) > 1:
        out["encoder"] = int(values[1])
    return out


def encode_can_trigger(seq: int, encoder: int = 0, fmt: str = DEFAULT_CAN_FORMAT) -> bytes:
    return struct.pack(fmt, seq, encoder)


# ---- filtering -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Verdict:
    accept: bool
    reason: str = ""  # "duplicate", "too soon" when dropped
    missed: int = 0  # triggers lost before this one (sequence gap)


@dataclass
class TriggerFilter:
    """Debounce, minimum interval and sequence-gap detection over events in arrival order.

    debounce_ns: an event repeating the previous one's seq (or, without seqs, arriving within this
    window of the previous event) is a duplicate. min_interval_ns: an event within this time of the
    last accepted one is dropped as too soon (the rig cannot take captures faster).
    """

    debounce_ns: int = 5_000_000
    min_interval_ns: int = 0
    received: int = 0
    accepted: int = 0
    duplicates: int = 0
    too_soon: int = 0
    missed: int = 0
    restarts: int = 0
    _last_seq: int | None = None
    _last_event_ns: int | None = None
    _last_accept_ns: int | None = None

    def check(self, ev: TriggerEvent) -> Verdict:
        self.received += 1
        prev_event_ns, self._last_event_ns = self._last_event_ns, ev.timestamp_ns
        missed = 0
        if ev.seq is not None and self._last_seq is not None:
            if ev.seq == self._last_seq:
                self.duplicates += 1
                return Verdict(False, "duplicate")
            if ev.seq > self._last_seq + 1:
                missed = ev.seq - self._last_seq - 1
            elif ev.seq < self._last_seq:
                self.restarts += 1  # controller rebooted or its counter wrapped: a new sequence starts
        elif ev.seq is None and prev_event_ns is not None and ev.timestamp_ns - prev_event_ns < self.debounce_ns:
            self.duplicates += 1
            return Verdict(False, "duplicate")
        if ev.seq is not None:
            self._last_seq = ev.seq
        self.missed += missed
        if self._last_accept_ns is not None and ev.timestamp_ns - self._last_accept_ns < self.min_interval_ns:
            self.too_soon += 1
            return Verdict(False, "too soon", missed)
        self._last_accept_ns = ev.timestamp_ns
        self.accepted += 1
        return Verdict(True, "", missed)

    def counts(self) -> dict:
        return {k: getattr(self, k) for k in ("received", "accepted", "duplicates", "too_soon", "missed", "restarts")}


# ---- sources -------------------------------------------------------------------------------------


class TriggerSource:
    """A reader thread that puts `TriggerEvent`s on `events`. Subclasses implement `_poll()`."""

    name = "trigger"

    def __init__(self, *, clock: Clock = time.monotonic_ns, reconnect_s: float = 0.2) -> None:
        self.events: queue.Queue[TriggerEvent] = queue.Queue()
        self.clock = clock
        self.reconnect_s = reconnect_s
        self.stats = {"events": 0, "garbage": 0, "reconnects": 0, "bus_errors": 0, "bus_off": 0}
        self.last_error = ""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> TriggerSource:
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"{self.name}-reader", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        self._close()

    def get(self, timeout: float | None = None) -> TriggerEvent | None:
        try:
            return self.events.get(timeout=timeout)
        except queue.Empty:
            return None

    def _emit(self, seq: int | None, payload: dict) -> None:
        self.stats["events"] += 1
        self.events.put(TriggerEvent(seq, self.name, self.clock(), payload))

    def _run(self) -> None:
        while not self._stop.is_set():
            self._poll()

    def _poll(self) -> None:
        raise NotImplementedError

    def _close(self) -> None:
        pass

    def _backoff(self) -> None:
        self._stop.wait(self.reconnect_s)


class SoftwareTrigger(TriggerSource):
    """The kiosk button / CLI: `fire()` emits the next event directly (no thread needed)."""

    name = "software"

    def __init__(self, *, clock: Clock = time.monotonic_ns) -> None:
        super().__init__(clock=clock)
        self._seq = 0

    def start(self) -> SoftwareTrigger:
        return self

    def fire(self, payload: dict | None = None, *, seq: int | None = None, timestamp_ns: int | None = None) -> TriggerEvent:
        self._seq = self._seq + 1 if seq is None else seq
        ev = TriggerEvent(self._seq, self.name, self.clock() if timestamp_ns is None else timestamp_ns, payload or {})
        self.stats["events"] += 1
        self.events.put(ev)
        return ev


class SerialTrigger(TriggerSource):
    """Line protocol from a photo-eye controller over a serial port (any pyserial URL).

    Lines that do not match `pattern` (a regex with a named group `seq`) are counted as garbage;
    over-long lines without a newline are dropped up to the next newline. A port that errors or
    vanishes is closed and reopened every `reconnect_s` until it is back.
    """

    name = "serial"

    def __init__(
        self,
        url: str,
        *,
        baudrate: int = 115200,
        pattern: str = DEFAULT_SERIAL_PATTERN,
        open_port: Callable[[], object] | None = None,
        max_line: int = 256,
        clock: Clock = time.monotonic_ns,
        reconnect_s: float = 0.2,
    ) -> None:
        super().__init__(clock=clock, reconnect_s=reconnect_s)
        self.url = url
        self.pattern = re.compile(pattern)
        if "seq" not in self.pattern.groupindex:
            raise ValueError(f"serial trigger pattern {pattern!r} needs a named group 'seq'")
        self.max_line = max_line
        self._open_port = open_port or (lambda: _open_serial(url, baudrate))
        self._port = None
        self._buf = b""
        self._skipping = False

    def _poll(self) -> None:
        import serial

        if self._port is None:
            try:
                self._port = self._open_port()
            except (serial.SerialException, OSError, ValueError) as e:
                self.last_error = f"serial port {self.url} unavailable: {e}"
                self._backoff()
                return
        try:
            data = self._port.read(max(1, self._port.in_waiting))
        except (serial.SerialException, OSError, TypeError, AttributeError) as e:
            # TypeError/AttributeError: pyserial's posix backend when the device node disappears.
            self.last_error = f"serial port {self.url} lost: {e}"
            self.stats["reconnects"] += 1
            self._close()
            self._buf = b""  # the line in flight is incomplete; a tail read after reconnecting fails the anchored pattern
            self._backoff()
            return
        if data:
            self._feed(data)

    def _feed(self, data: bytes) -> None:
        self._buf += data
        *lines, self._buf = self._buf.split(b"\n")
        for line in lines:
            if self._skipping:
                # The rest of a line already counted when it outgrew max_line: dropped, not counted again.
                self._skipping = False
                continue
            self._line(line)
        if len(self._buf) > self.max_line:
            self.stats["garbage"] += 1
            self._buf, self._skipping = b"", True

    def _line(self, line: bytes) -> None:
        if not line.strip():
            return
        parsed = parse_trigger_line(line, self.pattern)
        if parsed is None:
            self.stats["garbage"] += 1
            return
        seq = parsed.pop("seq")
        self._emit(seq, parsed)

    def _close(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            try:
                port.close()
            except Exception:  # noqa: BLE001 - a vanished port may fail to close; it is gone either way
                pass


def _open_serial(url: str, baudrate: int):
    import serial

    return serial.serial_for_url(url, baudrate=baudrate, timeout=0.1)


class CanTrigger(TriggerSource):
    """Trigger frames from a PLC on a CAN bus (SocketCAN in the field, python-can's `virtual` in tests).

    Frames with `arbitration_id` carry seq (and encoder count) per `payload_format`. Error frames
    are counted; a bus-off error frame, or a bus that raises on receive, is recovered by closing
    and reopening the bus (the kernel's restart-ms restarts the controller under SocketCAN).
    """

    name = "can"

    def __init__(
        self,
        *,
        interface: str = "socketcan",
        channel: str = "can0",
        arbitration_id: int = 0x181,
        payload_format: str = DEFAULT_CAN_FORMAT,
        bus_factory: Callable[[], object] | None = None,
        clock: Clock = time.monotonic_ns,
        reconnect_s: float = 0.2,
    ) -> None:
        super().__init__(clock=clock, reconnect_s=reconnect_s)
        self.arbitration_id = arbitration_id
        self.payload_format = payload_format
        self.channel = channel
        struct.calcsize(payload_format)  # a bad format fails here, at configuration time
        self._bus_factory = bus_factory or (lambda: _open_can(interface, channel))
        self._bus = None

    def _poll(self) -> None:
        import can

        if self._bus is None:
            try:
                self._bus = self._bus_factory()
            except (can.CanError, OSError, ValueError) as e:
                self.last_error = f"CAN bus {self.channel} unavailable: {e}"
                self._backoff()
                return
        try:
            msg = self._bus.recv(timeout=0.1)
        except (can.CanError, OSError) as e:
            self.last_error = f"CAN bus {self.channel} failed: {e}"
            self.stats["bus_errors"] += 1
            self._recover()
            return
        if msg is None:
            return
        if msg.is_error_frame:
            self.stats["bus_errors"] += 1
            if msg.arbitration_id & CAN_ERR_BUSOFF:
                self.stats["bus_off"] += 1
                self.last_error = f"CAN bus {self.channel} went bus-off; reopening"
                self._recover()
            return
        if msg.arbitration_id != self.arbitration_id:
            return  # other traffic on a shared bus
        decoded = decode_can_trigger(msg.data, self.payload_format)
        if decoded is None:
            self.stats["garbage"] += 1
            return
        seq = decoded.pop("seq")
        self._emit(seq, decoded)

    def _recover(self) -> None:
        self.stats["reconnects"] += 1
        self._close()
        self._backoff()

    def _close(self) -> None:
        bus, self._bus = self._bus, None
        if bus is not None:
            try:
                bus.shutdown()
            except Exception:  # noqa: BLE001 - a bus-off controller may refuse a clean shutdown
                pass


def _open_can(interface: str, channel: str):
    import can

    return can.Bus(interface=interface, channel=channel, receive_own_messages=False)
