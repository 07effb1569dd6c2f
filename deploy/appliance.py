"""The appliance behind the kiosk: rig acquisition, the calibration keeper and the pipeline service,
each on its own thread, summarised as one `ApplianceState` the operator screen draws.

`Appliance.from_config` runs a real rig from its `rig.toml`; `Appliance.simulated` runs all of it on the synthetic rig (the bundled sample's part on a simulated
conveyor) with a software trigger, so anyone can try the appliance without hardware. Its empty-rig
monitor views (the textured rig frame around the cameras) feed the keeper's drift check after every
capture; `knock(camera, degrees)` turns a camera physically, as a bump during maintenance would.
"""

from __future__ import annotations

import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from deploy.kiosk_state import Alarm, ApplianceState, CameraStatus, Progress, Verdict, drift_alarm, grade_twin

REPO = Path(__file__).resolve().parents[1]


def kiosk_pipeline_config(library_dir: str | Path, preset: str, rig=None, rig_toml: Path | None = None):
    """The kiosk's `PipelineConfig`: the line's rig.toml (`rig`, parsed; None: the defaults) as the service reads it,
    twins exported as ply and glb."""
    from deploy.steps import pipeline_config

    return pipeline_config(library_dir, preset, rig=rig, rig_toml=rig_toml, export_formats=("ply", "glb"))


class Appliance:
    """Cameras + trigger + capture store + calibration keeper + pipeline service, under `work_dir`.

    `monitor_views()` returns each camera's current view of the empty rig frame for the drift check;
    without it the keeper checks the committed capture's own images (background features).
    """

    def __init__(
        self,
        drivers,
        trigger_source,
        store,
        keeper,
        library_dir: Path,
        work_dir: Path,
        *,
        preset: str = "preview",
        interval_s: float = 20.0,
        backgrounds: dict[str, np.ndarray] | None = None,
        monitor_views=None,
        rig=None,
        rig_id: str = "rig",
        owns_dir: bool = False,
        closers=(),
        spill=None,
        rig_config=None,
        rig_toml: Path | None = None,
    ) -> None:
        from deploy.service import PipelineService
        from deploy.steps import make_step_runner

        self.dir = Path(work_dir)
        self._own_dir = owns_dir
        self.interval_s = interval_s
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._watching = threading.Event()
        self._acked: set[str] = set()
        self._message = "starting"
        self._progress: Progress | None = None
        self._stage_t0 = 0.0
        self._last_trigger = "none yet"
        self._checks: dict[str, dict] = {}
        self._keeper_note = ""
        self.drivers = list(drivers)
        self.rig = rig
        self.store = store
        self.keeper = keeper
        self.software_trigger = trigger_source
        self._monitor = monitor_views
        self._closers = list(closers)
        # Captures a read-only store could not take before the last stop wait in the spill: import them first.
        imported, problem = store.import_spill(spill) if spill is not None else ([], "")
        self._spill_problem = problem
        # Said on screen until the next capture.
        self._import_note = f"imported {len(imported)} capture(s) the read-only store could not take last time; " if imported else ""
        self.acquisition = self._open_acquisition(store, rig_id, rig_config, backgrounds, spill)
        cfg = kiosk_pipeline_config(library_dir, preset, rig_config, rig_toml)
        self.service = PipelineService(
            store.root, self.dir / "work", make_step_runner(cfg, progress=self._on_progress), max_queue=4, on_event=self._on_service_event
        )
        self._threads = [
            threading.Thread(target=self._acquire, name="kiosk-acquisition", daemon=True),
            threading.Thread(target=self._serve, name="kiosk-service", daemon=True),
            threading.Thread(target=self._auto_trigger, name="kiosk-trigger", daemon=True),
        ]
        for t in self._threads:
            t.start()
        if not self.acquisition.backgrounds:
            self._message = "no empty-rig frames yet: clear the rig and press b; then t takes a capture"
        else:
            self._message = "ready: press t to take a capture, w to start watching the line"

    def _open_acquisition(self, store, rig_id: str, rig_config, backgrounds, spill):
        """The cameras opened at the first one's size, and the acquisition that files their captures with the current
        calibration's id, uncertainty, units and up (rig.toml's `[simulation] up` where the calibration measured none)."""
        from calibration.calibfile import extrinsics_uncertainty
        from rig.acquisition import Acquisition, open_cameras
        from rig.camera import CameraSettings
        from simulation.up import capture_up

        first = self.drivers[0].camera
        settings = open_cameras(self.drivers, CameraSettings(first.width, first.height))
        calibration = self.keeper.store.load()
        return Acquisition(
            self.drivers,
            store,
            rig_id=rig_id,
            calibration_id=self._calibration_id(calibration),
            calibration_uncertainty=extrinsics_uncertainty(calibration),
            settings=settings,
            units=calibration.units,
            up_rig=capture_up(calibration.up_rig, (rig_config.simulation if rig_config else {}).get("up")),
            backgrounds=dict(backgrounds or {}),
            spill=spill,
        )

    @classmethod
    def from_config(
        cls, config_path: str | Path, library_dir: str | Path, work_dir: str | Path, *, preset: str = "cpu", interval_s: float = 20.0
    ) -> Appliance:
        """The real rig of a `rig.toml` (its cameras, trigger, store, calibration, [inspection] and [registration])."""
        from calibration.keeper import Keeper
        from rig.assembly import build_cameras, build_store, build_trigger, load_rig_calibration
        from rig.config import load_config
        from rig.store import Spill, default_spill_dir, lock_store
        from simulation.asset import rig_simulation_table

        cfg = load_config(config_path)
        kiosk_pipeline_config(library_dir, preset, cfg, Path(config_path))  # a bad [registration] refuses here, before the rig opens
        rig_simulation_table(config_path)  # and a bad [simulation] (its up goes into every capture)
        if cfg.calibration is None:
            raise ValueError(f'{config_path}: the kiosk needs the rig\'s calibration (set calibration = "calibration.json")')
        lock = lock_store(cfg.storage.root, "kiosk")  # one writer per store: a `rig watch` on it refuses the kiosk, and back
        calibration = load_rig_calibration(cfg.calibration).cameras
        drivers = build_cameras(cfg, calibration)
        trigger = build_trigger(cfg.trigger).start()
        store = build_store(cfg)
        work = Path(work_dir)
        work.mkdir(parents=True, exist_ok=True)
        spill = Spill(cfg.storage.spill or default_spill_dir(), store.root)
        return cls(
            drivers,
            trigger,
            store,
            Keeper(cfg.calibration),
            Path(library_dir),
            work,
            preset=preset,
            interval_s=interval_s,
            rig_id=cfg.rig_id,
            closers=[trigger.stop, lock.release],
            spill=spill,
            rig_config=cfg,
            rig_toml=Path(config_path),
        )

    @classmethod
    def simulated(
        cls,
        work_dir: str | Path | None = None,
        *,
        views: int = 8,
        size: tuple[int, int] = (320, 240),
        preset: str = "preview",
        interval_s: float = 20.0,
        library_meshes: str | Path | None = None,
    ) -> Appliance:
        """The whole appliance on the synthetic rig: the bundled sample's part on a simulated conveyor,
        a software trigger, and the textured rig frame around the cameras as the keeper's reference."""
        from calibration.calibfile import CalibrationDoc, CalibrationStore
        from calibration.keeper import Keeper
        from calibration.simulated import render_planes, rig_frame_scene
        from reconstruction.library import build_library
        from rig.assembly import simulated_cameras
        from rig.store import CaptureStore, Spill
        from rig.triggers import SoftwareTrigger

        owns = work_dir is None
        work = Path(tempfile.mkdtemp(prefix="cadsplat-kiosk-")) if owns else Path(work_dir)
        work.mkdir(parents=True, exist_ok=True)
        lib_dir = work / "library"
        if not (lib_dir / "library.json").exists():
            build_library(library_meshes or REPO / "sample" / "library_meshes", lib_dir, progress=False)
        drivers, rig = simulated_cameras(views, *size)
        calib_path = work / "calibration.json"
        if not calib_path.exists():
            CalibrationStore(calib_path).commit(CalibrationDoc({d.camera_id: d.camera for d in drivers}, source="board"))
        keeper = Keeper(calib_path)
        walls, _ = rig_frame_scene(np.random.default_rng(0), fiducials=False)

        def monitor() -> dict[str, np.ndarray]:
            return {d.camera_id: render_planes(rig.true_camera(i), walls, supersample=2) for i, d in enumerate(drivers)}

        keeper.set_reference(monitor())
        store = CaptureStore(work / "store", min_free_bytes=256 << 20)
        # The simulated rig keeps its spill in its own work directory, not in the user's state directory.
        app = cls(
            drivers,
            SoftwareTrigger(),
            store,
            keeper,
            lib_dir,
            work,
            preset=preset,
            interval_s=interval_s,
            monitor_views=monitor,
            rig=rig,
            rig_id="simulated-rig",
            owns_dir=owns,
            closers=[rig.close],
            spill=Spill(work / "spill", store.root),
        )
        if not app.acquisition.backgrounds:
            app.take_background()  # the simulated belt starts empty
            app._message = "ready: press t to take a capture, w to start watching the line"
        return app

    # ---- rig and keeper ------------------------------------------------------------------------

    @staticmethod
    def _calibration_id(calibration) -> str:
        return f"calibration-v{calibration.version:04d}"

    def knock(self, camera: str, degrees: float, axis=(0.3, 1.0, 0.2)) -> None:
        """Turn a simulated camera physically (a bump during maintenance); its calibration stays."""
        from calibration.so3 import axis_angle_to_matrix

        if self.rig is None:
            raise ValueError("only a simulated camera can be knocked")
        a = np.asarray(axis, np.float64)
        index = [d.camera_id for d in self.drivers].index(camera)
        self.rig.knock(index, axis_angle_to_matrix(np.radians(degrees) * a / np.linalg.norm(a)))

    def _check_drift(self, capture_id: str) -> None:
        from calibration.calibfile import extrinsics_uncertainty
        from calibration.keeper import capture_images

        views = self._monitor() if self._monitor else capture_images(self.store.read(capture_id))
        rec = self.keeper.check(views, capture=capture_id)
        with self._lock:
            self._checks = rec.get("cameras", {})
            self._keeper_note = rec["action"] if rec["action"] not in ("none", "reference set") else ""
        if rec["action"].startswith("corrected"):
            calib = self.keeper.store.load()
            if self.rig is not None:
                for i, d in enumerate(self.drivers):
                    self.rig.set_calibration(i, calib.cameras[d.camera_id].c2w)
            self.acquisition.calibration_id = self._calibration_id(calib)
            self.acquisition.calibration_uncertainty = extrinsics_uncertainty(calib)

    def _acquire(self) -> None:
        def outcome(out) -> None:
            with self._lock:
                self._last_trigger = f"#{out.trigger.seq} {time.strftime('%H:%M:%S')} {out.status}"
                self._import_note = ""
            if out.status == "committed":
                try:
                    self._check_drift(out.capture_id)
                except (OSError, ValueError) as e:  # a full disk must not end acquisition: the check is retried with the next capture
                    with self._lock:
                        self._keeper_note = f"drift check not recorded ({getattr(e, 'strerror', None) or e})"

        self.acquisition.run(self.software_trigger, self._stop, on_outcome=outcome)

    def _auto_trigger(self) -> None:
        while not self._stop.is_set():
            if self._watching.is_set():
                if hasattr(self.software_trigger, "fire"):
                    self.software_trigger.fire({"source": "line"})
                self._stop.wait(self.interval_s)
            else:
                self._stop.wait(0.1)

    # ---- service -------------------------------------------------------------------------------

    def _serve(self) -> None:
        while not self._stop.is_set():
            if not self.service.run_once():
                self._stop.wait(0.5)

    def _on_progress(self, stage: str, i: int, n: int) -> None:
        from deploy.service import StepInterrupted

        if self._stop.is_set():
            # Closing: leave the step for the next start (the engine resumes from its checkpoint).
            raise StepInterrupted(stage)
        now = time.monotonic()
        with self._lock:
            p = self._progress
            if p is None or p.stage != stage:
                self._stage_t0 = now
            frac = (i + 1) / max(n, 1)
            eta = (now - self._stage_t0) / frac * (1 - frac) if frac > 0.02 else None
            self._progress = Progress(p.capture_id if p else "", stage, frac, eta)

    def _on_service_event(self, e) -> None:
        with self._lock:
            if e.kind == "step-started":
                self._progress = Progress(e.capture_id, e.step, 0.0)
            elif e.kind in ("job-done", "job-failed"):
                self._progress = None
            if e.kind == "job-failed":
                self._message = f"capture {e.capture_id} could not be turned into a twin: {e.detail.get('error', '')}"

    # ---- ApplianceBackend ----------------------------------------------------------------------

    def state(self) -> ApplianceState:
        from calibration.keeper import RECALIBRATE

        with self._lock:
            checks = dict(self._checks)
            progress, last_trigger, note = self._progress, self._last_trigger, self._keeper_note
        cams = []
        for d in self.drivers:
            c = checks.get(d.camera_id, {})
            h = d.health()
            cams.append(
                CameraStatus(d.camera_id, h.ok, c.get("status", "—"), c.get("rotation_deg"), c.get("effect_px"), "" if h.ok else h.detail)
            )
        alarms = [a for a in (drift_alarm(c) for c in cams) if a]
        if note and not any(c.calibration == RECALIBRATE for c in cams):
            alarms.append(Alarm(f"keeper:{note}", f"Calibration keeper {note}."))
        disk_full = next((a for a in (self.acquisition.stopped, self.store.alarm, self.service.state) if a.startswith("STOPPED")), "")
        if self._spill_problem:
            alarms.append(Alarm("spill", self._spill_problem))
        if self.store.alarm or self.service.state:
            alarms.append(Alarm("disk", "; ".join(a for a in (self.store.alarm, self.service.state) if a)))
        for job in self.service.jobs.jobs("failed"):
            alarms.append(Alarm(f"job:{job.id}", f"Capture {job.capture_id} failed ({job.error}) — press r to re-run."))
        alarms = tuple(Alarm(a.key, a.text, a.key in self._acked) for a in alarms)
        done = self.service.jobs.jobs("done")
        verdict = None
        if done:
            job = done[-1]
            reg, rec = job.steps["register"]["output"], job.steps["reconstruct"]["output"]
            grade, advice = grade_twin(reg["score"], rec["fit_iou"])
            preview = Path(rec["twin"]) / "renders"
            first = sorted(preview.glob("*.png"))
            verdict = Verdict(
                job.capture_id,
                rec["model_id"],
                reg["score"],
                rec["fit_iou"],
                grade,
                advice,
                str(first[0]) if first else "",
                rec.get("inspection", {}).get("line", ""),
            )
        queued = tuple(j.capture_id for j in self.service.jobs.jobs("queued"))
        return ApplianceState(
            watching=self._watching.is_set(),
            trigger_source=f"software (line every {self.interval_s:.0f}s)" if self._watching.is_set() else "software",
            last_trigger=last_trigger,
            cameras=tuple(cams),
            captures=len(self.store.capture_ids()),
            quarantined=len(self.store.quarantined_ids()),
            disk_free_gb=self.store.disk_free() / 1e9,
            queue=queued,
            progress=progress,
            last_twin=verdict,
            alarms=alarms,
            message=self._import_note + self._message,
            disk_full=disk_full,
        )

    def toggle_watch(self) -> None:
        if self._watching.is_set():
            self._watching.clear()
            self._message = "stopped watching the line"
        else:
            self._watching.set()
            self._message = "watching the line"

    def trigger(self) -> None:
        """A capture now, whatever the line's trigger source is (the kiosk button)."""
        from rig.triggers import TriggerEvent

        src = self.software_trigger
        if hasattr(src, "fire"):
            src.fire({"source": "kiosk"})
        else:
            src.events.put(TriggerEvent(None, "kiosk", time.monotonic_ns(), {"source": "kiosk"}))
        self._message = "capture requested"

    def take_background(self) -> None:
        """Take the empty-rig reference (the rig must be empty): a new version in the store (rig.reference)."""
        out = self.acquisition.take_reference("taken at the kiosk")
        if out.status == "reference":
            self._message = f"empty-rig frames taken for {len(self.acquisition.backgrounds)} cameras ({out.capture_id})"
        else:
            self._message = out.reason

    def rerun(self) -> None:
        failed = self.service.jobs.jobs("failed")
        if not failed:
            self._message = "nothing to re-run: no job has failed"
            return
        self.service.jobs.retry(failed[-1].id)
        self._message = f"re-running {failed[-1].capture_id}"

    def acknowledge(self) -> None:
        for a in self.state().alarms:
            self._acked.add(a.key)

    def close(self) -> None:
        if self._stop.is_set():
            return
        self._stop.set()
        self.service.stop()
        for t in self._threads:
            t.join(timeout=60)
        for out in self.acquisition.close():  # captures still held: committed now, spilled, or failed (each one sentence)
            if out.status != "committed":
                print(f"{out.status} {out.capture_id}: {out.reason}", file=sys.stderr)
        for close in self._closers:
            close()
        if self._own_dir:
            shutil.rmtree(self.dir, ignore_errors=True)
