"""Simulated cameras behind the driver protocol, so the whole appliance runs without hardware.

- `SyntheticRig` + `SyntheticCamera`: the synthetic rig renderer (rig/synthetic.py) as N drivers.
  Each trigger brings a new part down the conveyor: its placement on the belt is a deterministic
  function of the trigger's seq (`conveyor_placement`), and all views of a trigger come from one render.
  A negative seq is the belt with no part on it (what the empty-rig reference is taken of).
- `PatternCamera`: a test-pattern camera (a per-camera gradient with a bar that moves with seq).
  Costs almost nothing to make, so benchmarks measure acquisition and the store, not rendering.
"""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from calibration.camera import Camera, look_at_c2w
from rig.camera import CameraError, CameraSettings, Frame, Health

GOLDEN_ANGLE_DEG = 137.50776405
_FILL = 0.8  # fraction of the shorter image side the part's bounding sphere spans


def conveyor_placement(seq: int, *, lateral_m: float = 0.01) -> tuple[float, tuple[float, float]]:
    """Yaw (deg) and belt offset (m) of the part that trigger `seq` photographs: a new yaw for each
    part (golden-angle steps, so successive parts never repeat) and a small lateral offset."""
    return (seq * GOLDEN_ANGLE_DEG) % 360.0, (0.0, lateral_m * float(np.sin(seq * 1.7)))


def procedural_part(size_m: tuple[float, float, float] = (0.08, 0.05, 0.03), texels: int = 256):
    """A box with a checker-and-gradient texture (each face its own UV patch): a part to render when no mesh ships."""
    import trimesh

    from rig.render_mujoco import TexturedMesh

    tm = trimesh.creation.box(extents=size_m)
    tm.unmerge_vertices()
    v = np.asarray(tm.vertices)
    n = np.asarray(tm.face_normals)
    uv = np.zeros((len(v), 2))
    for f, face in enumerate(np.asarray(tm.faces)):
        axis = int(np.argmax(np.abs(n[f])))
        a, b = [k for k in range(3) if k != axis]
        uv[face] = (v[face][:, [a, b]] / np.asarray(size_m)[[a, b]] + 0.5) * 0.9 + 0.05
    y, x = np.mgrid[0:texels, 0:texels]
    checker = ((x // 32 + y // 32) % 2).astype(np.float32)
    tex = np.stack([60 + 150 * x / texels, 60 + 120 * checker, 200 - 140 * y / texels], -1).astype(np.uint8)
    return TexturedMesh(np.asarray(tm.vertices, np.float64), np.asarray(tm.faces, np.int64), uv, tex)


class SyntheticRig:
    """The synthetic rig renderer shared by its camera drivers; renders all views of a trigger once.

    `cameras` are the rig's cameras (OpenCV c2w in the rig frame: origin on the belt, z up);
    `scene` is a `rig.synthetic.SyntheticScene` without backdrop (the belt moves with the part).
    All rendering happens on one thread, the one MuJoCo's GL context belongs to. `jitter_ns`
    spreads the views' exposure times, to exercise the sync tolerance.
    """

    def __init__(self, scene, cameras: list[Camera], *, noise_std: float = 0.01, jitter_ns: int = 200_000, seed: int = 0) -> None:
        self.scene = scene
        self.cameras = list(cameras)
        self.noise_std = noise_std
        self.jitter_ns = int(jitter_ns)
        self.seed = seed
        self._lock = threading.Lock()
        self._gl = ThreadPoolExecutor(max_workers=1, thread_name_prefix="synthetic-render")
        self._seq: int | None = None
        self._images: np.ndarray | None = None
        self._t0 = 0
        self._knocks: dict[int, np.ndarray] = {}

    def knock(self, index: int, rotation: np.ndarray) -> None:
        """Camera `index` physically turns by `rotation` [3, 3] (in its own frame) while its calibration,
        what `camera` reports, stays as it was: the drift the calibration keeper must notice."""
        with self._lock:
            self._knocks[index] = np.asarray(rotation, np.float64) @ self._knocks.get(index, np.eye(3))
            self._seq = None

    def set_calibration(self, index: int, c2w: np.ndarray) -> None:
        """The rig's calibration of camera `index` becomes `c2w` (a recalibration or a drift
        correction); the camera itself stays where it physically is."""
        with self._lock:
            true_r = self.true_camera(index).c2w[:3, :3]
            self.cameras[index] = self.cameras[index].with_c2w(c2w)
            self._knocks[index] = np.asarray(c2w, np.float64)[:3, :3].T @ true_r
            self._seq = None

    def true_camera(self, index: int) -> Camera:
        """Where camera `index` really is (its calibration plus any knock)."""
        cam = self.cameras[index]
        if index not in self._knocks:
            return cam
        c2w = cam.c2w.copy()
        c2w[:3, :3] = c2w[:3, :3] @ self._knocks[index]
        return cam.with_c2w(c2w)

    @classmethod
    def from_mesh(
        cls, mesh, n_views: int, *, width: int = 640, height: int = 480, fov_deg: float = 45.0, elevations_deg=(15.0, 40.0), **kw
    ) -> SyntheticRig:
        """A ring rig sized to the part. `mesh`: a mesh file path or a `TexturedMesh`."""
        from rig.synthetic import SyntheticScene, load_textured_mesh, ring_rig

        if isinstance(mesh, (str, Path)):
            mesh = load_textured_mesh(mesh, texture_size=512)
        lo, hi = mesh.bounds
        fov_short = 2 * np.arctan(np.tan(np.radians(fov_deg) / 2) * min(width, height) / width)
        radius = mesh.radius / np.sin(_FILL * fov_short / 2)
        cameras = ring_rig(
            n_views,
            radius=radius,
            elevations_deg=elevations_deg,
            target=(0.0, 0.0, (hi[2] - lo[2]) / 2),
            width=width,
            height=height,
            fov_deg=fov_deg,
        )
        return cls(SyntheticScene(mesh, backdrop=False), cameras, **kw)

    def sim3_rig_to_object(self, seq: int):
        from rig.synthetic import conveyor_sim3

        yaw, offset = conveyor_placement(seq)
        return conveyor_sim3(self.scene.mesh, yaw, offset)

    def views(self, seq: int) -> tuple[np.ndarray, int]:
        """RGB uint8 [V, H, W, 3] of trigger `seq` (a negative seq: the empty belt) and the host time it was
        exposed (rendered once per seq)."""
        with self._lock:
            if self._seq != seq:
                self._t0 = time.monotonic_ns()
                if seq < 0:
                    self._images = self._render_empty()
                else:
                    sim3 = self.sim3_rig_to_object(seq)
                    true = [self.true_camera(i) for i in range(len(self.cameras))]
                    cams_obj = [c.with_c2w(sim3.apply_to_c2w(c.c2w)) for c in true]
                    rgb, _ = self._gl.submit(self.scene.render, cams_obj, noise_std=self.noise_std, seed=self.seed + seq).result()
                    self._images = np.asarray(rgb)
                self._seq = seq
            return self._images, self._t0

    def _render_empty(self) -> np.ndarray:
        cams = [self.true_camera(i) for i in range(len(self.cameras))]
        rgb, _ = self._gl.submit(self.scene.render, cams, noise_std=self.noise_std, seed=self.seed, object_visible=False).result()
        return np.asarray(rgb)

    def empty_views(self) -> np.ndarray:
        """RGB uint8 [V, H, W, 3] of the rig with no part in it (what background subtraction compares with)."""
        with self._lock:
            return self._render_empty()

    def drivers(self, prefix: str = "cam") -> list[SyntheticCamera]:
        return [SyntheticCamera(f"{prefix}{i:02d}", self, i) for i in range(len(self.cameras))]

    def close(self) -> None:
        self._gl.submit(self.scene.close).result()
        self._gl.shutdown()


class SyntheticCamera:
    """View `index` of a `SyntheticRig`."""

    def __init__(self, camera_id: str, rig: SyntheticRig, index: int) -> None:
        self.camera_id = camera_id
        self.rig = rig
        self.index = index
        self._seq: int | None = None
        self._open = False
        self._frames = 0
        self._settings = CameraSettings(rig.cameras[index].width, rig.cameras[index].height)

    @property
    def camera(self) -> Camera:
        return self.rig.cameras[self.index]

    def open(self) -> None:
        self._open = True

    def configure(self, settings: CameraSettings) -> CameraSettings:
        cam = self.camera
        if (settings.width, settings.height) != (cam.width, cam.height):
            raise CameraError(
                f"{self.camera_id}: the synthetic rig renders {cam.width}x{cam.height}, not {settings.width}x{settings.height}"
            )
        # A renderer's "exposure" is fixed: report it locked, identical across views.
        self._settings = CameraSettings(
            cam.width, cam.height, exposure_us=10_000, iso=100, white_balance_k=5500, focus=settings.focus, sync="software"
        )
        return self._settings

    def arm(self, seq: int) -> None:
        self._seq = seq

    def grab(self, timeout_s: float) -> Frame:
        if not self._open or self._seq is None:
            raise CameraError(f"{self.camera_id}: grab before open and arm")
        images, t0 = self.rig.views(self._seq)
        self._frames += 1
        jitter = (self.index * 7919) % (2 * self.rig.jitter_ns + 1) - self.rig.jitter_ns if self.rig.jitter_ns else 0
        return Frame(self.camera_id, images[self.index], t0 + jitter, _settings_dict(self._settings))

    def close(self) -> None:
        self._open = False

    def health(self) -> Health:
        return Health(self.camera_id, self._open, "synthetic view" if self._open else "closed", self._frames)


class PatternCamera:
    """A test-pattern camera: a per-camera colour gradient with a bar at a seq-dependent column.

    `camera` is a pinhole on a ring around the rig origin (`index` of `n` views), so its captures
    are valid captures. It exposes when armed, as a frame-synced sensor does on its trigger edge;
    `time_ns` is the clock its timestamps come from.
    """

    def __init__(
        self, camera_id: str, *, index: int = 0, n: int = 1, width: int = 640, height: int = 480, time_ns=time.monotonic_ns
    ) -> None:
        self.camera_id = camera_id
        self.index = index
        az = 2 * np.pi * index / max(n, 1)
        eye = np.array([0.5 * np.cos(az), 0.5 * np.sin(az), 0.3])
        self._camera = Camera.from_fov(np.deg2rad(50.0), width, height, look_at_c2w(eye, np.zeros(3)))
        self._time_ns = time_ns
        self._base: np.ndarray | None = None
        self._seq: int | None = None
        self._exposed_ns = 0
        self._open = False
        self._frames = 0
        self._settings = CameraSettings(width, height)

    @property
    def camera(self) -> Camera:
        return self._camera

    def open(self) -> None:
        w, h = self._camera.width, self._camera.height
        u = np.linspace(40, 215, w, dtype=np.float32)[None, :]
        v = np.linspace(40, 215, h, dtype=np.float32)[:, None]
        hue = (self.index * 53) % 160
        self._base = np.stack(np.broadcast_arrays(u + 0 * v, v + 0 * u, np.full((h, w), 40 + hue, np.float32)), -1).astype(np.uint8)
        self._open = True

    def configure(self, settings: CameraSettings) -> CameraSettings:
        if (settings.width, settings.height) != (self._camera.width, self._camera.height):
            self._camera = self._camera.scaled(settings.width, settings.height)
            self.open()
        self._settings = CameraSettings(
            settings.width,
            settings.height,
            settings.exposure_us or 10_000,
            settings.iso or 100,
            settings.white_balance_k or 5500,
            settings.focus,
            settings.sync,
        )
        return self._settings

    def arm(self, seq: int) -> None:
        self._seq = seq
        self._exposed_ns = self._time_ns()

    def grab(self, timeout_s: float) -> Frame:
        if not self._open or self._seq is None:
            raise CameraError(f"{self.camera_id}: grab before open and arm")
        img = self._base.copy()
        w = img.shape[1]
        if self._seq >= 0:  # a negative seq is the empty belt: no bar
            x = (self._seq * 37) % max(w - 16, 1)
            img[:, x : x + 16] = 230
        self._frames += 1
        return Frame(self.camera_id, img, self._exposed_ns, _settings_dict(self._settings))

    def close(self) -> None:
        self._open = False

    def health(self) -> Health:
        return Health(self.camera_id, self._open, "test pattern" if self._open else "closed", self._frames)


def _settings_dict(s: CameraSettings) -> dict:
    return {"exposure_us": s.exposure_us, "iso": s.iso, "white_balance_k": s.white_balance_k, "focus": s.focus, "sync": s.sync}
