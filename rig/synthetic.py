"""The synthetic rig: a camera driver that photographs a textured mesh instead of a real object.

Frames. The object frame is the mesh's own frame (metres). The rig frame is the calibration's:
origin at the ring centre on the conveyor surface, z up. The object lies on the conveyor at a yaw
and an offset, so `sim3_rig_to_object` (x_obj = s R x_rig + t) is never the identity by default;
pass `rig_to_object` for any other Sim(3) (scale != 1 models a rig calibrated in other units).

Captures store camera poses in the rig frame, as a calibration would give them; `gt.json` holds
the truth: the Sim(3), the true object-frame poses of every train and held-out camera, and the
calibration error applied to the recorded train extrinsics (images always come from true poses).
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from calibration.camera import Camera, look_at_c2w
from calibration.capture import FrameData, write_capture
from calibration.fileio import atomic_write_json
from calibration.sim3 import Sim3
from calibration.so3 import axis_angle_to_matrix
from rig.render_mujoco import Light, SyntheticScene, TexturedMesh, load_textured_mesh

__all__ = [
    "Light",
    "SyntheticScene",
    "TexturedMesh",
    "load_textured_mesh",
    "ring_rig",
    "conveyor_sim3",
    "perturb_extrinsics",
    "synth_dataset",
    "TRAIN_ELEVATIONS_DEG",
    "HELDOUT_ELEVATIONS_DEG",
]

TRAIN_ELEVATIONS_DEG = (15.0, 40.0)
HELDOUT_ELEVATIONS_DEG = (10.0, 27.5, 45.0)
_FILL = 0.85  # fraction of the shorter image side the object's bounding sphere spans at the ring radius
_SYNC_TIMESTAMP_NS = 1_700_000_000_000_000_000  # one trigger: every view of a capture shares it


def ring_rig(
    n_views: int,
    *,
    radius: float,
    elevations_deg: Sequence[float] = (20.0,),
    target: Sequence[float] = (0.0, 0.0, 0.0),
    width: int = 320,
    height: int = 240,
    fov_deg: float = 45.0,
    up: Sequence[float] = (0.0, 0.0, 1.0),
    azimuth_offset_deg: float = 0.0,
) -> list[Camera]:
    """Cameras on rings around `target`, looking at it, OpenCV c2w in the frame `target` and `up` are given in.

    The views are split over the elevations as evenly as possible (earlier rings get the extra
    views); successive rings are staggered by half an azimuth step so no two views line up.
    fov_deg: horizontal field of view; square pixels, centred principal point.
    """
    if n_views < 1:
        raise ValueError(f"a ring rig needs at least one view, got {n_views}")
    if radius <= 0:
        raise ValueError(f"ring radius must be positive, got {radius}")
    if not elevations_deg:
        raise ValueError("a ring rig needs at least one elevation")
    target = np.asarray(target, np.float64)
    up = np.asarray(up, np.float64)
    up = up / np.linalg.norm(up)
    e1 = np.cross([0.0, 1.0, 0.0] if abs(up[1]) < 0.9 else [0.0, 0.0, 1.0], up)  # up = z gives e1 = x, e2 = y
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    counts = [len(c) for c in np.array_split(np.arange(n_views), len(elevations_deg))]
    cameras = []
    for ring, (elev, count) in enumerate(zip(elevations_deg, counts)):
        el = np.radians(elev)
        for k in range(count):
            az = np.radians(azimuth_offset_deg + (k + 0.5 * ring) * 360.0 / count)
            eye = target + radius * (np.cos(el) * (np.cos(az) * e1 + np.sin(az) * e2) + np.sin(el) * up)
            cameras.append(Camera.from_fov(np.radians(fov_deg), width, height, look_at_c2w(eye, target, up)))
    return cameras


def conveyor_sim3(mesh: TexturedMesh, yaw_deg: float, offset: Sequence[float]) -> Sim3:
    """`sim3_rig_to_object` of a mesh lying on the conveyor (rig z = 0), turned by `yaw_deg` about rig z, its
    footprint centre at rig (offset x, offset y); offset[2], if given, lifts it."""
    lo, hi = mesh.bounds
    rest = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])  # object point that sits at the offset
    off = np.zeros(3)
    off[: len(offset)] = offset
    yaw = np.radians(yaw_deg)
    rz = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
    # x_rig = Rz (x_obj - rest) + off  <=>  x_obj = Rz^T x_rig + rest - Rz^T off
    return Sim3(1.0, rz.T, rest - rz.T @ off)


def perturb_extrinsics(
    c2w: np.ndarray, rng: np.random.Generator, *, sigma_deg: float, sigma_translation: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Calibration error: poses [V, 4, 4] -> (perturbed poses, rotation vectors deg [V, 3], centre shifts [V, 3]).

    Each camera turns about its own axes by a rotation vector with i.i.d. N(0, sigma_deg^2)
    components and its centre moves by i.i.d. N(0, sigma_translation^2) per axis (frame units).
    """
    c2w = np.asarray(c2w, np.float64)
    rotvec_deg = rng.normal(0.0, sigma_deg, (len(c2w), 3)) if sigma_deg > 0 else np.zeros((len(c2w), 3))
    shift = rng.normal(0.0, sigma_translation, (len(c2w), 3)) if sigma_translation > 0 else np.zeros((len(c2w), 3))
    out = c2w.copy()
    out[:, :3, :3] = c2w[:, :3, :3] @ axis_angle_to_matrix(np.radians(rotvec_deg))
    out[:, :3, 3] += shift
    return out, rotvec_deg, shift


def synth_dataset(
    mesh_path: str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    views: int = 9,
    heldout: int = 36,
    size: tuple[int, int] = (320, 240),
    seed: int = 0,
    elevations_deg: Sequence[float] = TRAIN_ELEVATIONS_DEG,
    heldout_elevations_deg: Sequence[float] = HELDOUT_ELEVATIONS_DEG,
    fov_deg: float = 45.0,
    radius: float | None = None,
    cameras: Sequence[Camera] | None = None,
    calib_noise_deg: float = 0.0,
    calib_noise_mm: float = 0.0,
    object_yaw_deg: float | None = None,
    object_offset: Sequence[float] | None = None,
    backdrop: bool = False,
    lighting_jitter: float = 0.0,
    noise_std: float = 0.0,
    rig_to_object: Sim3 | None = None,
    texture_size: int | None = 1024,
    progress: Callable[[str, int, int], None] | None = None,
) -> dict:
    """Render a train capture, a held-out orbit capture and the ground truth; returns the gt dict.

    Writes out_dir/train and out_dir/heldout (captures with masks/ and background/) and
    out_dir/gt.json. Existing captures are never overwritten (CaptureError).

    cameras: explicit train cameras in the rig frame (e.g. from a calibration) instead of rings;
    their intrinsics and sizes are used as given. object_yaw_deg / object_offset (rig metres, x y
    [z]): the object's pose on the conveyor; None draws them from `seed`. rig_to_object overrides
    the conveyor pose altogether. calib_noise_deg / calib_noise_mm: per-axis sigma of the error
    added to the RECORDED train extrinsics. lighting_jitter in [0, 1]: per-view change of the key
    light's direction (up to ~35 deg at 1) and intensity (up to +-40% at 1). noise_std: sensor
    noise, full-scale units. progress(stage, done, total) is called after every rendered view.
    """
    mesh_path = Path(mesh_path)
    out_dir = Path(out_dir)
    width, height = int(size[0]), int(size[1])
    if views < 1 and cameras is None:
        raise ValueError(f"need at least one train view, got {views}")
    if heldout < 0:
        raise ValueError(f"held-out view count must be >= 0, got {heldout}")
    if width < 8 or height < 8:
        raise ValueError(f"image size {width}x{height} is too small (at least 8x8)")
    for name, value in (
        ("calib_noise_deg", calib_noise_deg),
        ("calib_noise_mm", calib_noise_mm),
        ("noise_std", noise_std),
        ("lighting_jitter", lighting_jitter),
    ):
        if not (np.isfinite(value) and value >= 0):
            raise ValueError(f"{name} must be a finite number >= 0, got {value}")
    rng = np.random.default_rng(seed)
    mesh = load_textured_mesh(mesh_path, texture_size=texture_size)

    yaw = float(rng.uniform(0.0, 360.0)) if object_yaw_deg is None else float(object_yaw_deg)
    offset = rng.uniform(-0.02, 0.02, 2) if object_offset is None else np.asarray(object_offset, np.float64)
    sim3 = conveyor_sim3(mesh, yaw, offset) if rig_to_object is None else rig_to_object
    object_to_rig = sim3.inverse()
    scale = sim3.scale  # metres per rig unit

    # Ring geometry in the rig frame: aim at the object's centre, distance so it fills _FILL of the frame.
    centre_rig = object_to_rig.apply(mesh.bounds.mean(0))
    target = np.array([centre_rig[0], centre_rig[1], centre_rig[2]]) if rig_to_object is not None else np.array([0.0, 0.0, centre_rig[2]])
    if radius is None:
        fov_short = 2 * np.arctan(np.tan(np.radians(fov_deg) / 2) * min(width, height) / width)
        radius = mesh.radius / np.sin(_FILL * fov_short / 2) / scale
    if cameras is None:
        train_rig = ring_rig(
            views, radius=radius, elevations_deg=elevations_deg, target=target, width=width, height=height, fov_deg=fov_deg
        )
    else:
        train_rig = list(cameras)
        if not train_rig:
            raise ValueError("explicit camera list is empty")
    heldout_rig = (
        ring_rig(
            heldout,
            radius=radius,
            elevations_deg=heldout_elevations_deg,
            target=target,
            width=train_rig[0].width,
            height=train_rig[0].height,
            fov_deg=fov_deg,
            azimuth_offset_deg=7.0,
        )
        if heldout
        else []
    )

    recorded, rotvec_deg, shift = perturb_extrinsics(
        np.stack([c.c2w for c in train_rig]), rng, sigma_deg=calib_noise_deg, sigma_translation=calib_noise_mm * 1e-3 / scale
    )
    train_obj = [c.with_c2w(sim3.apply_to_c2w(c.c2w)) for c in train_rig]
    heldout_obj = [c.with_c2w(sim3.apply_to_c2w(c.c2w)) for c in heldout_rig]

    key_down = sim3.rotation @ np.array([0.3, 0.2, -1.0])  # the rig's ceiling lamp, in the object frame

    def lights(n: int) -> list[Light]:
        out = []
        for _ in range(n):
            tilt = axis_angle_to_matrix(rng.normal(0.0, 0.35 * lighting_jitter, 3))
            gain = float(np.clip(1.0 + rng.uniform(-0.4, 0.4) * lighting_jitter, 0.2, 2.0))
            d = tilt @ key_down
            out.append(Light(direction=tuple(d / np.linalg.norm(d)), diffuse=0.6 * gain, headlight=0.35 * gain))
        return out

    train_lights, heldout_lights = lights(len(train_obj)), lights(len(heldout_obj))
    noise_seed = int(rng.integers(2**31))
    with SyntheticScene(mesh, backdrop=backdrop, floor_to_object=sim3) as scene:

        def shoot(stage: str, cams: list[Camera], lts: list[Light], seed_offset: int):
            images, masks, bgs = [], [], []
            for i, (cam, lt) in enumerate(zip(cams, lts)):
                img, msk = scene.render([cam], light=lt, noise_std=noise_std, seed=noise_seed + seed_offset + i)
                bg, _ = scene.render([cam], light=lt, noise_std=noise_std, seed=noise_seed + seed_offset + 10_000 + i, object_visible=False)
                images.append(img[0]), masks.append(msk[0]), bgs.append(bg[0])
                if progress:
                    progress(stage, i + 1, len(cams))
            return images, masks, bgs

        train = shoot("train", train_obj, train_lights, 0)
        held = shoot("heldout", heldout_obj, heldout_lights, 100_000) if heldout_obj else None

    mesh_sha = hashlib.sha256(mesh_path.read_bytes()).hexdigest()
    meta = {
        "rig_id": "synthetic",
        "calibration_id": f"synthetic-seed{seed}" + ("-perturbed" if calib_noise_deg or calib_noise_mm else ""),
        "trigger": "software",
        "synthetic": {"mesh": mesh_path.name, "seed": seed},
    }
    if calib_noise_deg or calib_noise_mm:
        # The recorded extrinsics are off by this much per axis, as a keeper's calibration states its own uncertainty.
        meta["calibration_uncertainty"] = {"rotation_deg": float(calib_noise_deg), "translation_mm": float(calib_noise_mm)}
    recorded_cams = [c.with_c2w(m) for c, m in zip(train_rig, recorded)]
    _write(out_dir / "train", "cam", recorded_cams, train, meta)
    if held:
        exact = {k: v for k, v in meta.items() if k != "calibration_uncertainty"}
        _write(out_dir / "heldout", "orbit", heldout_rig, held, {**exact, "calibration_id": f"synthetic-seed{seed}"})

    gt = {
        "mesh": _mesh_reference(mesh_path, out_dir),
        "mesh_name": mesh_path.parent.name if mesh_path.stem == "textured" else mesh_path.stem,
        "mesh_sha256": mesh_sha,
        "units": "m",
        "seed": seed,
        "size": [train_rig[0].width, train_rig[0].height],
        "views": len(train_rig),
        "heldout": len(heldout_rig),
        "sim3_rig_to_object": sim3.to_dict(),
        "object_pose": {"yaw_deg": yaw if rig_to_object is None else None, "offset": offset.tolist() if rig_to_object is None else None},
        "ring": {
            "radius_rig": float(radius),
            "elevations_deg": list(elevations_deg) if cameras is None else None,
            "heldout_elevations_deg": list(heldout_elevations_deg),
            "target_rig": target.tolist(),
            "fov_deg": fov_deg,
        },
        "train_intrinsics": [c.K.tolist() for c in train_rig],
        "train_c2w_object": [c.c2w.tolist() for c in train_obj],
        "heldout_c2w_object": [c.c2w.tolist() for c in heldout_obj],
        "train_c2w_rig_true": [c.c2w.tolist() for c in train_rig],
        "calib_noise": {
            "sigma_deg": calib_noise_deg,
            "sigma_mm": calib_noise_mm,
            "rotvec_deg": rotvec_deg.tolist(),
            "centre_shift_rig": shift.tolist(),
        },
        "render": {
            "backdrop": backdrop,
            "lighting_jitter": lighting_jitter,
            "noise_std": noise_std,
            "texture_size": texture_size,
            "renderer": "mujoco",
        },
    }
    atomic_write_json(out_dir / "gt.json", gt)
    return gt


def _mesh_reference(mesh_path: Path, out_dir: Path) -> str:
    """The mesh path relative to gt.json's directory when it lives beside it (a relocatable sample), else absolute."""
    mesh_abs, out_abs = mesh_path.resolve(), out_dir.resolve()
    try:
        return os.path.relpath(mesh_abs, out_abs) if out_abs.parent in mesh_abs.parents or out_abs in mesh_abs.parents else str(mesh_abs)
    except ValueError:
        return str(mesh_abs)


def _write(root: Path, prefix: str, cameras: Sequence[Camera], shots, meta: dict) -> None:
    images, masks, bgs = shots
    frames = [
        FrameData(f"{prefix}{i:02d}", img, cam, f"{prefix}{i:02d}", _SYNC_TIMESTAMP_NS, msk)
        for i, (cam, img, msk) in enumerate(zip(cameras, images, masks))
    ]
    write_capture(root, frames, backgrounds={f.camera_id: bg for f, bg in zip(frames, bgs)}, meta=meta)
