"""Synchronized acquisition: trigger -> a frame from every camera -> validated -> committed or quarantined.

Every trigger ends in exactly one outcome, and each is counted: `committed` (a complete, verified
capture in the store), `quarantined` (kept with its reason), `refused` (no room on the disk for a
whole capture, or a camera down and reconnecting by itself; decided before its frames are taken:
nothing is stored, nothing lost), `late` (the trigger waited longer than the part stays in view),
`dropped` (a duplicate or too-soon trigger), `held` (the store could take neither the capture nor a
quarantine entry, e.g. it went read-only mid-write: the frames stay in memory and are written as
soon as it can), `spilled` (held until the rig stopped: the capture waits in the spill, see below)
or `reference` (the belt was empty: a new empty-rig reference was taken, see rig.reference).
`failed` only when the rig stops with a held capture that the spill could not take either.

A held capture is written to the spill (rig.store.Spill, on another filesystem) at once, not only
at close: a SIGKILL or power loss while the store is read-only then loses nothing either. Once the
store takes the capture from memory its spill copy is removed; if the rig stops first, the spill
copy is what the store imports on its next start.

The empty-rig reference is taken on command (`take_reference`), on schedule (`reference_every_s`,
while no trigger waits) and whenever a trigger says the belt is empty (payload `belt: "empty"`,
e.g. a serial pattern with a `(?P<belt>empty)` group). Cameras are armed with seq -1 for it.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from calibration.capture import CaptureError, FrameData
from rig.camera import CameraDriver, CameraError, CameraSettings, Frame
from rig.reference import ReferenceError
from rig.store import CaptureStore, Spill, StoreError, is_enospc
from rig.triggers import TriggerEvent, TriggerFilter, TriggerSource

OUTCOMES = ("committed", "quarantined", "refused", "late", "dropped", "failed", "reference", "held", "spilled")
EMPTY_BELT_SEQ = -1  # what cameras are armed with for an empty-rig reference (the simulated rig renders no part)


@dataclass(frozen=True)
class Thresholds:
    """What makes a capture valid. Frames of one capture must lie within `sync_tolerance_ns` of
    each other; a frame is black below `black_level` mean intensity and saturated above
    `saturated_fraction` clipped pixels."""

    sync_tolerance_ns: int = 5_000_000
    black_level: float = 0.02
    saturated_fraction: float = 0.5
    grab_timeout_s: float = 2.0
    max_trigger_age_ns: int = 2_000_000_000


@runtime_checkable
class SelfRecovering(Protocol):
    """A driver that re-opens a lost device in the background (OAK); the rig waits for it instead of reopening it inline."""

    @property
    def reconnecting(self) -> bool: ...


@dataclass(frozen=True)
class Outcome:
    status: str
    trigger: TriggerEvent
    capture_id: str = ""
    reason: str = ""
    latency_ns: int = 0
    state_change: str = ""  # "stopped" on the first refusal for a full disk, "resumed" on the first capture after


def brightness(image: np.ndarray) -> tuple[float, float]:
    """Mean intensity in [0, 1] and fraction of clipped pixels (any channel at 255) of uint8 [H, W, 3].

    A 1/16 subsample: validation runs on every frame and this is plenty to tell black from lit.
    """
    sub = np.asarray(image)[::4, ::4]
    clipped = sub >= 255
    return float(sub.mean()) / 255.0, float(clipped.any(axis=-1).mean() if sub.ndim == 3 else clipped.mean())


def validate_frames(frames: dict[str, Frame], camera_ids: Sequence[str], sizes: dict[str, tuple[int, int]], th: Thresholds) -> list[str]:
    """Problems that make a capture invalid (empty list: valid). `sizes`: camera_id -> (width, height)."""
    problems = []
    missing = [c for c in camera_ids if c not in frames]
    if missing:
        problems.append(f"no frame from {', '.join(missing)}")
    for cid, f in frames.items():
        img = np.asarray(f.image)
        w, h = sizes[cid]
        if img.dtype != np.uint8 or img.shape != (h, w, 3):
            problems.append(f"{cid} frame is {img.dtype} {img.shape}, expected uint8 ({h}, {w}, 3)")
            continue
        mean, clipped = brightness(img)
        if mean < th.black_level:
            problems.append(f"{cid} frame is black (mean {mean:.3f})")
        elif clipped > th.saturated_fraction:
            problems.append(f"{cid} frame is saturated ({100 * clipped:.0f}% clipped)")
    if len(frames) > 1:
        ts = [f.timestamp_ns for f in frames.values()]
        spread = max(ts) - min(ts)
        if spread > th.sync_tolerance_ns:
            problems.append(f"frames are {spread / 1e6:.2f} ms apart, beyond the {th.sync_tolerance_ns / 1e6:.2f} ms sync tolerance")
    return problems


def agree_photometry(cameras: Sequence[CameraDriver], settings: CameraSettings) -> CameraSettings:
    """Lock every camera to one exposure, gain and white balance so all views agree photometrically.

    Fixed values are applied as they are; otherwise each camera converges once and the median of
    what they chose is locked on all of them.
    """
    if settings.locked:
        applied = [cam.configure(settings) for cam in cameras]
        return applied[0]
    chosen = [cam.configure(settings) for cam in cameras]
    med = lambda xs: int(np.median([x for x in xs if x is not None])) if any(x is not None for x in xs) else None  # noqa: E731
    locked = replace(
        settings,
        exposure_us=med([s.exposure_us for s in chosen]),
        iso=med([s.iso for s in chosen]),
        white_balance_k=med([s.white_balance_k for s in chosen]),
    )
    for cam in cameras:
        cam.configure(locked)
    return locked


@dataclass
class _Held:
    """A capture whose frames the store could not take yet: committed (or quarantined, with `reason`) later.
    `spilled`: where its copy in the spill is ('' while it has none); `spill_error`: why it has none."""

    event: TriggerEvent
    capture_id: str
    data: list
    meta: dict
    backgrounds: dict | None
    quarantine_reason: str = ""
    spilled: str = ""
    spill_error: str = ""


@dataclass
class Acquisition:
    """Turns triggers into stored captures. `cameras` must be open (see `open_cameras`)."""

    cameras: Sequence[CameraDriver]
    store: CaptureStore
    rig_id: str = "rig"
    calibration_id: str = "uncalibrated"
    # The calibration's stated extrinsic uncertainty; the engine picks per-camera pose correction when it is large.
    calibration_uncertainty: dict | None = None
    units: str | None = None  # the calibration's, when metric: captures then state their scale
    up_rig: dict | None = None  # the calibration's up (calibfile `up_rig`), when it measured one: captures carry it to the twin
    thresholds: Thresholds = field(default_factory=Thresholds)
    trigger_filter: TriggerFilter = field(default_factory=TriggerFilter)
    settings: CameraSettings | None = None
    clock: Callable[[], int] = time.monotonic_ns
    counts: dict = field(default_factory=lambda: dict.fromkeys(OUTCOMES, 0))
    # Empty-rig frames per camera, stored with every capture so masks come from background subtraction;
    # by default the store's current reference (rig.reference), whose id every capture records.
    backgrounds: dict[str, np.ndarray] = field(default_factory=dict)
    background_id: str = ""
    reference_every_s: float | None = None
    spill: Spill | None = None  # where held captures go when the store stays unwritable (None: nowhere, they fail at close)

    def __post_init__(self) -> None:
        ids = [c.camera_id for c in self.cameras]
        if len(set(ids)) != len(ids) or not ids:
            raise ValueError(f"camera ids must be unique and at least one camera is needed, got {ids}")
        self._pool = ThreadPoolExecutor(max_workers=len(self.cameras), thread_name_prefix="grab")
        self._next_seq = 0
        self.stopped = ""
        self.reference_note = ""
        self.held: list[_Held] = []
        self._reference_t = time.monotonic()
        if not self.backgrounds:
            try:
                ref = self.store.references.current()
            except ReferenceError as e:
                ref, self.reference_note = None, f"{e}; take a new one with the belt empty"
            if ref is not None:
                self.backgrounds, self.background_id = dict(ref.frames), ref.reference_id

    def capture_bytes(self) -> int:
        """Disk a capture needs at most: its PNG frames (and the reference copy), with room for the manifests."""
        raw = sum(c.camera.width * c.camera.height * 3 for c in self.cameras)
        return int(1.1 * raw * (2 if self.backgrounds else 1)) + 4096 * (len(self.cameras) + 4)

    # ---- the empty-rig reference ---------------------------------------------------------------

    def take_reference(self, reason: str) -> Outcome:
        """Grab every camera with the belt empty and store the frames as the next reference version."""
        event = TriggerEvent(EMPTY_BELT_SEQ, "reference", self.clock(), {"belt": "empty", "why": reason})
        self._reference_t = time.monotonic()
        frames, errors = self._grab_all(EMPTY_BELT_SEQ)
        sizes = {c.camera_id: (c.camera.width, c.camera.height) for c in self.cameras}
        problems = [f"{cid}: {msg}" for cid, msg in sorted(errors.items())]
        problems += validate_frames(frames, [c.camera_id for c in self.cameras if c.camera_id not in errors], sizes, self.thresholds)
        if problems:
            return self._count(Outcome("refused", event, reason=f"empty-rig reference not taken: {'; '.join(problems)}"))
        try:
            ref = self.store.with_reserve(lambda: self.store.references.commit({cid: f.image for cid, f in frames.items()}, reason))
        except (OSError, ReferenceError) as e:
            return self._count(Outcome("refused", event, reason=f"empty-rig reference not stored: {getattr(e, 'strerror', None) or e}"))
        self.backgrounds, self.background_id, self.reference_note = dict(ref.frames), ref.reference_id, ""
        return self._count(Outcome("reference", event, ref.reference_id, reason))

    # ---- one trigger ---------------------------------------------------------------------------

    def handle(self, event: TriggerEvent) -> Outcome:
        """Filter one trigger and, if it passes, capture it. Always returns (and counts) one outcome."""
        verdict = self.trigger_filter.check(event)
        if not verdict.accept:
            return self._count(Outcome("dropped", event, reason=verdict.reason))
        if event.payload.get("belt") == "empty":
            return self.take_reference("the trigger said the belt is empty")
        age = self.clock() - event.timestamp_ns
        if age > self.thresholds.max_trigger_age_ns:
            return self._count(Outcome("late", event, reason=f"trigger waited {age / 1e9:.2f} s, longer than the part stays in view"))
        if self.camera_alarm:
            return self._count(Outcome("refused", event, reason=f"{self.camera_alarm}; no capture taken"))
        # Room for the whole capture (and its id) is made sure of before any frame is taken.
        capture_id = ""
        if self.store.room_for(self.capture_bytes()):
            try:
                capture_id = self.store.reserve_id()
            except StoreError:
                pass
        if not capture_id:
            change = "" if self.stopped else "stopped"
            self.stopped = self.store.alarm
            return self._count(Outcome("refused", event, reason=self.store.alarm, state_change=change))
        out = self.capture(event, capture_id)
        if self.stopped:
            self.stopped = ""
            out = replace(out, state_change="resumed")
        return self._count(out)

    def capture(self, event: TriggerEvent, capture_id: str | None = None) -> Outcome:
        seq = event.seq if event.seq is not None else self._next_seq
        self._next_seq = seq + 1
        if self.camera_alarm:
            return Outcome("refused", event, reason=f"{self.camera_alarm}; no capture taken")
        capture_id = capture_id or self.store.reserve_id()
        frames, errors = self._grab_all(seq)
        if self.camera_alarm:
            # A camera dropped while this capture was in flight: refused whole, none of its frames stored, so
            # the outcome names no capture (its reserved number stays a gap in the store's counter).
            return Outcome("refused", event, "", f"{self.camera_alarm}; the capture in flight was refused whole")
        cams = {c.camera_id: c for c in self.cameras}
        data = [FrameData(cid, f.image, cams[cid].camera, cid, f.timestamp_ns) for cid, f in sorted(frames.items())]
        spread = int(np.ptp([f.timestamp_ns for f in frames.values()])) if frames else 0
        meta = {
            "rig_id": self.rig_id,
            "calibration_id": self.calibration_id,
            "trigger": event.to_dict(),
            "sync_spread_ns": spread,
            "trigger_to_exposure_ns": {cid: f.timestamp_ns - event.timestamp_ns for cid, f in sorted(frames.items())},
            "camera_settings": {cid: f.settings for cid, f in sorted(frames.items())},
        }
        if self.calibration_uncertainty is not None:
            meta["calibration_uncertainty"] = dict(self.calibration_uncertainty)
        if self.units is not None:
            meta["units"] = self.units
        if self.up_rig is not None:
            meta["up_rig"] = dict(self.up_rig)
        if self.backgrounds:
            meta["background_id"] = self.background_id or "unversioned"
        sizes = {c.camera_id: (c.camera.width, c.camera.height) for c in self.cameras}
        problems = [f"{cid}: {msg}" for cid, msg in sorted(errors.items())]
        problems += validate_frames(frames, [c.camera_id for c in self.cameras if c.camera_id not in errors], sizes, self.thresholds)
        if problems:
            return self._quarantine(event, capture_id, "; ".join(problems), data, meta)
        backgrounds = {k: v for k, v in self.backgrounds.items() if k in frames} or None
        try:
            self.store.commit(capture_id, data, meta, backgrounds=backgrounds)
        except (OSError, ValueError, StoreError) as e:
            if isinstance(e, OSError) and not is_enospc(e):
                # The store cannot be written at all (read-only, I/O error): keep the frames, write them later.
                return self._hold(_Held(event, capture_id, data, meta, backgrounds), f"the store could not be written ({e.strerror or e})")
            what = "disk full while writing" if is_enospc(e) else "write failed"
            return self._quarantine(event, capture_id, f"{what}: {e}", data, meta)
        return Outcome("committed", event, capture_id, latency_ns=self.clock() - event.timestamp_ns)

    def _quarantine(self, event: TriggerEvent, capture_id: str, reason: str, data: list[FrameData], meta: dict) -> Outcome:
        try:
            self.store.quarantine(capture_id, reason, data, meta, {"trigger": event.to_dict()})
        except StoreError as e:
            return self._hold(_Held(event, capture_id, data, meta, None, reason), f"{reason}; and {e}")
        return Outcome("quarantined", event, capture_id, reason, self.clock() - event.timestamp_ns)

    def _hold(self, held: _Held, why: str) -> Outcome:
        self.held.append(held)
        where = f" (a copy is in the spill at {held.spilled})" if self._spill(held) else ""
        return Outcome(
            "held",
            held.event,
            held.capture_id,
            f"{why}; its frames are kept in memory{where} and written as soon as the store can take them",
        )

    def _spill(self, held: _Held) -> bool:
        """Write a held capture to the spill once; False (with `spill_error`) when there is none or it cannot take it."""
        if held.spilled:
            return True
        if self.spill is None:
            held.spill_error = "no spill directory is configured"
            return False
        meta = {**held.meta, "quarantined": held.quarantine_reason} if held.quarantine_reason else held.meta
        try:
            held.spilled = str(self.spill.write(held.capture_id, held.data, meta, None if held.quarantine_reason else held.backgrounds))
        except (OSError, CaptureError) as e:
            held.spill_error = f"the spill at {self.spill.dir} could not take it either ({getattr(e, 'strerror', None) or e})"
            return False
        return True

    def flush_held(self) -> list[Outcome]:
        """Write the held captures the store can now take, oldest first; their outcomes replace "held" in the counts."""
        out = []
        while self.held:
            h = self.held[0]
            try:
                if h.quarantine_reason:
                    self.store.quarantine(h.capture_id, h.quarantine_reason, h.data, h.meta, {"trigger": h.event.to_dict()})
                else:
                    self.store.commit(h.capture_id, h.data, h.meta, backgrounds=h.backgrounds)
            except (OSError, ValueError, StoreError):
                break
            self.held.pop(0)
            self.counts["held"] -= 1
            if h.spilled:
                try:
                    self.spill.discard(Path(h.spilled))
                except OSError:
                    pass  # the store copy verifies: the next import drops the spill copy
            status = "quarantined" if h.quarantine_reason else "committed"
            out.append(
                self._count(
                    Outcome(
                        status,
                        h.event,
                        h.capture_id,
                        h.quarantine_reason or "written after the store could take it again",
                        self.clock() - h.event.timestamp_ns,
                    )
                )
            )
        return out

    def _grab_all(self, seq: int) -> tuple[dict[str, Frame], dict[str, str]]:
        """Arm every camera, then grab from all at once. A camera that failed before is reopened first."""
        errors: dict[str, str] = {}
        for cam in self.cameras:
            try:
                if not cam.health().ok and not (isinstance(cam, SelfRecovering) and cam.reconnecting):
                    self._reopen(cam)
                cam.arm(seq)
            except CameraError as e:
                errors[cam.camera_id] = str(e)
        live = [c for c in self.cameras if c.camera_id not in errors]
        futures = {c.camera_id: self._pool.submit(c.grab, self.thresholds.grab_timeout_s) for c in live}
        frames = {}
        for cid, fut in futures.items():
            try:
                frames[cid] = fut.result()
            except CameraError as e:
                errors[cid] = str(e)
            except Exception as e:  # noqa: BLE001 - a driver bug must quarantine the capture, not kill the rig
                errors[cid] = f"driver error: {type(e).__name__}: {e}"
        return frames, errors

    def _reopen(self, cam: CameraDriver) -> None:
        try:
            cam.close()
        except CameraError:
            pass
        cam.open()
        cam.configure(self.settings or CameraSettings(cam.camera.width, cam.camera.height))

    @property
    def camera_alarm(self) -> str:
        """'' while every camera is up; else which cameras are down and reconnecting, by name."""
        why: dict[str, list[str]] = {}
        for c in self.cameras:
            if isinstance(c, SelfRecovering) and c.reconnecting:
                why.setdefault(c.health().detail, []).append(c.camera_id)
        return "; ".join(
            f"camera{'s' if len(ids) > 1 else ''} {', '.join(ids)} {'are' if len(ids) > 1 else 'is'} down: {detail}"
            for detail, ids in why.items()
        )

    def _count(self, out: Outcome) -> Outcome:
        self.counts[out.status] += 1
        return out

    # ---- the loop ------------------------------------------------------------------------------

    @property
    def taken(self) -> int:
        """Captures taken: committed, quarantined or held in memory."""
        return self.counts["committed"] + self.counts["quarantined"] + self.counts["held"]

    def run(
        self,
        source: TriggerSource,
        stop: threading.Event,
        *,
        max_captures: int | None = None,
        on_outcome: Callable[[Outcome], None] | None = None,
        on_idle: Callable[[], None] | None = None,
        poll_s: float = 0.1,
    ) -> None:
        """Handle triggers until `stop` is set or `max_captures` are taken. A capture in flight always completes.

        Held captures count as taken: at the cap the loop ends whatever it holds and `close` writes them (or
        spills them); waiting for the store instead would keep taking triggers past the cap."""
        while not stop.is_set() and (max_captures is None or self.taken < max_captures):
            for out in self.flush_held() if self.held else ():
                if on_outcome is not None:
                    on_outcome(out)
            ev = source.get(timeout=poll_s)
            if ev is None:
                if self.reference_every_s is not None and time.monotonic() - self._reference_t >= self.reference_every_s:
                    out = self.take_reference(f"scheduled (every {self.reference_every_s:g} s)")
                    if on_outcome is not None:
                        on_outcome(out)
                if on_idle is not None:
                    on_idle()
                continue
            out = self.handle(ev)
            if on_outcome is not None:
                on_outcome(out)

    def close(self) -> list[Outcome]:
        """Close the cameras; returns what became of the held captures: committed now, else spilled (the store
        imports them on its next start), else failed (the spill could not take them either)."""
        self._pool.shutdown(wait=True)
        for cam in self.cameras:
            try:
                cam.close()
            except CameraError:
                pass
        out = self.flush_held()
        for h in self.held:
            self.counts["held"] -= 1
            if self._spill(h):
                out.append(
                    self._count(
                        Outcome(
                            "spilled",
                            h.event,
                            h.capture_id,
                            f"the store stayed unwritable until the rig stopped; the capture waits "
                            f"in the spill at {h.spilled} and goes into the store on its next start (or `cadsplat store import-spill`)",
                        )
                    )
                )
            else:
                out.append(
                    self._count(
                        Outcome(
                            "failed",
                            h.event,
                            h.capture_id,
                            f"the rig stopped before the store could be written and {h.spill_error}; its frames are lost",
                        )
                    )
                )
        self.held.clear()
        return out


def open_cameras(cameras: Sequence[CameraDriver], settings: CameraSettings) -> CameraSettings:
    """Open every camera and lock them to one photometric setting; returns the setting in force."""
    for cam in cameras:
        cam.open()
    return agree_photometry(cameras, settings)
