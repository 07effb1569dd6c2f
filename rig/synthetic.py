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
    mesh_path, out_dir = Path(mesh_path), Path(out_dir)
    width, height = int(size[0]), int(size[1])
    _check_synth_args(views, heldout, width, height, cameras, calib_noise_deg, calib_noise_mm, noise_std, lighting_jitter)
    rng = np.random.default_rng(seed)
    mesh = load_textured_mesh(mesh_path, texture_size=texture_size)
    sim3, object_pose = _object_pose(mesh, rng, object_yaw_deg, object_offset, rig_to_object)

    target, radius = _ring_target_and_radius(mesh, sim3, (width, height), fov_deg, radius, centred=rig_to_object is not None)
    train_rig, heldout_rig = _train_and_heldout_rigs(
        cameras, views, heldout, radius, target, (width, height), fov_deg, elevations_deg, heldout_elevations_deg
    )
    recorded, rotvec_deg, shift = perturb_extrinsics(
        np.stack([c.c2w for c in train_rig]), rng, sigma_deg=calib_noise_deg, sigma_translation=calib_noise_mm * 1e-3 / sim3.scale
    )
    train_obj = [c.with_c2w(sim3.apply_to_c2w(c.c2w)) for c in train_rig]
    heldout_obj = [c.with_c2w(sim3.apply_to_c2w(c.c2w)) for c in heldout_rig]
    train, held = _render(mesh, sim3, train_obj, heldout_obj, rng, backdrop, lighting_jitter, noise_std, progress)

    meta = _capture_meta(mesh_path, seed, calib_noise_deg, calib_noise_mm)
    _write_captures(out_dir, meta, seed, [c.with_c2w(m) for c, m in zip(train_rig, recorded)], train, heldout_rig, held)

    gt = {
        **_mesh_truth(mesh_path, out_dir),
        "units": "m",
        "seed": seed,
        "size": [train_rig[0].width, train_rig[0].height],
        "views": len(train_rig),
        "heldout": len(heldout_rig),
        "sim3_rig_to_object": sim3.to_dict(),
        "object_pose": object_pose,
        "ring": _ring_truth(radius, elevations_deg if cameras is None else None, heldout_elevations_deg, target, fov_deg),
        **_camera_truth(train_rig, train_obj, heldout_obj),
        "calib_noise": _calib_noise_truth(calib_noise_deg, calib_noise_mm, rotvec_deg, shift),
        "render": _render_settings(backdrop, lighting_jitter, noise_std, texture_size),
    }
    atomic_write_json(out_dir / "gt.json", gt)
    return gt


def _object_pose(
    mesh: TexturedMesh,
    rng: np.random.Generator,
    object_yaw_deg: float | None,
    object_offset: Sequence[float] | None,
    rig_to_object: Sim3 | None,
) -> tuple[Sim3, dict]:
    """The rig-to-object Sim(3) and gt.json's `object_pose`: `rig_to_object` when given (no yaw or offset), else
    the part on the conveyor at yaw `object_yaw_deg` and offset `object_offset` (rig metres, x y [z]); None draws
    them from `rng` (drawn even when `rig_to_object` is given, so the draws that follow do not depend on it)."""
    yaw = float(rng.uniform(0.0, 360.0)) if object_yaw_deg is None else float(object_yaw_deg)
    offset = rng.uniform(-0.02, 0.02, 2) if object_offset is None else np.asarray(object_offset, np.float64)
    if rig_to_object is not None:
        return rig_to_object, {"yaw_deg": None, "offset": None}
    return conveyor_sim3(mesh, yaw, offset), {"yaw_deg": yaw, "offset": offset.tolist()}


def _render(
    mesh: TexturedMesh,
    sim3: Sim3,
    train_obj: list[Camera],
    heldout_obj: list[Camera],
    rng: np.random.Generator,
    backdrop: bool,
    lighting_jitter: float,
    noise_std: float,
    progress: Callable[[str, int, int], None] | None,
) -> tuple[tuple, tuple | None]:
    """The train and held-out shots (`_shoot`: images, masks, backgrounds; held-out None without cameras) from the
    object-frame cameras, under the rig's ceiling lamp jittered per view (`_jittered_lights`), on the floor
    (and backdrop) placed by the rig-to-object `sim3`."""
    key_down = sim3.rotation @ np.array([0.3, 0.2, -1.0])  # the rig's ceiling lamp, in the object frame
    train_lights = _jittered_lights(rng, key_down, len(train_obj), lighting_jitter)
    heldout_lights = _jittered_lights(rng, key_down, len(heldout_obj), lighting_jitter)
    noise_seed = int(rng.integers(2**31))
    with SyntheticScene(mesh, backdrop=backdrop, floor_to_object=sim3) as scene:
        train = _shoot(scene, "train", train_obj, train_lights, noise_std, noise_seed, progress)
        held = _shoot(scene, "heldout", heldout_obj, heldout_lights, noise_std, noise_seed + 100_000, progress) if heldout_obj else None
    return train, held


def _check_synth_args(
    views: int,
    heldout: int,
    width: int,
    height: int,
    cameras: Sequence[Camera] | None,
    calib_noise_deg: float,
    calib_noise_mm: float,
    noise_std: float,
    lighting_jitter: float,
) -> None:
    """Raise ValueError naming the first synth_dataset argument that is out of range."""
    if views < 1 and cameras is None:
        raise ValueError(f"need at least one train view, got {views}")
    if heldout < 0:
        raise ValueError(f"held-out view count must be >= 0, got {heldout}")
    if width < 8 or height < 8:
        raise ValueError(f"image size {width}x{height} is too small (at least 8x8)")
    non_negative = {
        "calib_noise_deg": calib_noise_deg,
        "calib_noise_mm": calib_noise_mm,
        "noise_std": noise_std,
        "lighting_jitter": lighting_jitter,
    }
    for name, value in non_negative.items():
        if not (np.isfinite(value) and value >= 0):
            raise ValueError(f"{name} must be a finite number >= 0, got {value}")


def _ring_target_and_radius(
    mesh: TexturedMesh, sim3: Sim3, size: tuple[int, int], fov_deg: float, radius: float | None, *, centred: bool
) -> tuple[np.ndarray, float]:
    """The ring's aim point [3] in the rig frame and its radius (rig units) so the object fills _FILL of the frame.

    centred aims at the object's centre; otherwise at the rig axis at the object's height.
    """
    width, height = size
    scale = sim3.scale  # metres per rig unit
    centre_rig = sim3.inverse().apply(mesh.bounds.mean(0))
    target = np.array([centre_rig[0], centre_rig[1], centre_rig[2]]) if centred else np.array([0.0, 0.0, centre_rig[2]])
    if radius is None:
        fov_short = 2 * np.arctan(np.tan(np.radians(fov_deg) / 2) * min(width, height) / width)
        radius = mesh.radius / np.sin(_FILL * fov_short / 2) / scale
    return target, radius


def _train_and_heldout_rigs(
    cameras: Sequence[Camera] | None,
    views: int,
    heldout: int,
    radius: float,
    target: np.ndarray,
    size: tuple[int, int],
    fov_deg: float,
    elevations_deg: Sequence[float],
    heldout_elevations_deg: Sequence[float],
) -> tuple[list[Camera], list[Camera]]:
    """The train cameras (explicit, else a ring) and the held-out orbit ring, in the rig frame."""
    width, height = size
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
    return train_rig, heldout_rig


def _camera_truth(train_rig: list[Camera], train_obj: list[Camera], heldout_obj: list[Camera]) -> dict:
    """gt.json's per-camera truth: train intrinsics, object-frame poses and the true rig-frame train poses."""
    return {
        "train_intrinsics": [c.K.tolist() for c in train_rig],
        "train_c2w_object": [c.c2w.tolist() for c in train_obj],
        "heldout_c2w_object": [c.c2w.tolist() for c in heldout_obj],
        "train_c2w_rig_true": [c.c2w.tolist() for c in train_rig],
    }


def _ring_truth(
    radius: float, elevations_deg: Sequence[float] | None, heldout_elevations_deg: Sequence[float], target: np.ndarray, fov_deg: float
) -> dict:
    """gt.json's record of the camera rings: radius (rig units), elevations (None for explicit train cameras), aim point [3]."""
    return {
        "radius_rig": float(radius),
        "elevations_deg": list(elevations_deg) if elevations_deg is not None else None,
        "heldout_elevations_deg": list(heldout_elevations_deg),
        "target_rig": target.tolist(),
        "fov_deg": fov_deg,
    }


def _calib_noise_truth(sigma_deg: float, sigma_mm: float, rotvec_deg: np.ndarray, shift: np.ndarray) -> dict:
    """gt.json's record of the calibration error added: per-axis sigmas and the drawn rotations [N, 3] and shifts [N, 3]."""
    return {"sigma_deg": sigma_deg, "sigma_mm": sigma_mm, "rotvec_deg": rotvec_deg.tolist(), "centre_shift_rig": shift.tolist()}


def _render_settings(backdrop: bool, lighting_jitter: float, noise_std: float, texture_size: int | None) -> dict:
    """gt.json's record of how the views were rendered."""
    return {
        "backdrop": backdrop,
        "lighting_jitter": lighting_jitter,
        "noise_std": noise_std,
        "texture_size": texture_size,
        "renderer": "mujoco",
    }


def _jittered_lights(rng: np.random.Generator, key_down: np.ndarray, n: int, lighting_jitter: float) -> list[Light]:
    """n key lights around key_down [3] (object frame), each tilted and scaled at random by lighting_jitter."""
    out = []
    for _ in range(n):
        tilt = axis_angle_to_matrix(rng.normal(0.0, 0.35 * lighting_jitter, 3))
        gain = float(np.clip(1.0 + rng.uniform(-0.4, 0.4) * lighting_jitter, 0.2, 2.0))
        d = tilt @ key_down
        out.append(Light(direction=tuple(d / np.linalg.norm(d)), diffuse=0.6 * gain, headlight=0.35 * gain))
    return out


def _shoot(
    scene: SyntheticScene,
    stage: str,
    cams: list[Camera],
    lights: list[Light],
    noise_std: float,
    seed: int,
    progress: Callable[[str, int, int], None] | None,
) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """Images, object masks and object-free backgrounds rendered from every camera under its light."""
    images, masks, bgs = [], [], []
    for i, (cam, lt) in enumerate(zip(cams, lights)):
        img, msk = scene.render([cam], light=lt, noise_std=noise_std, seed=seed + i)
        bg, _ = scene.render([cam], light=lt, noise_std=noise_std, seed=seed + 10_000 + i, object_visible=False)
        images.append(img[0]), masks.append(msk[0]), bgs.append(bg[0])
        if progress:
            progress(stage, i + 1, len(cams))
    return images, masks, bgs


def _capture_meta(mesh_path: Path, seed: int, calib_noise_deg: float, calib_noise_mm: float) -> dict:
    """The train capture's meta block: rig and calibration ids, and the stated calibration uncertainty when perturbed."""
    meta = {
        "rig_id": "synthetic",
        "calibration_id": f"synthetic-seed{seed}" + ("-perturbed" if calib_noise_deg or calib_noise_mm else ""),
        "trigger": "software",
        "synthetic": {"mesh": mesh_path.name, "seed": seed},
    }
    if calib_noise_deg or calib_noise_mm:
        # The recorded extrinsics are off by this much per axis, as a keeper's calibration states its own uncertainty.
        meta["calibration_uncertainty"] = {"rotation_deg": float(calib_noise_deg), "translation_mm": float(calib_noise_mm)}
    return meta


def _mesh_truth(mesh_path: Path, out_dir: Path) -> dict:
    """gt.json's mesh fields: where the mesh is (`_mesh_reference`), its name and its sha256."""
    return {
        "mesh": _mesh_reference(mesh_path, out_dir),
        "mesh_name": mesh_path.parent.name if mesh_path.stem == "textured" else mesh_path.stem,
        "mesh_sha256": hashlib.sha256(mesh_path.read_bytes()).hexdigest(),
    }


def _mesh_reference(mesh_path: Path, out_dir: Path) -> str:
    """The mesh path relative to gt.json's directory when it lives beside it (a relocatable sample), else absolute."""
    mesh_abs, out_abs = mesh_path.resolve(), out_dir.resolve()
    try:
        return os.path.relpath(mesh_abs, out_abs) if out_abs.parent in mesh_abs.parents or out_abs in mesh_abs.parents else str(mesh_abs)
    except ValueError:
        return str(mesh_abs)


def _write_captures(
    out_dir: Path,
    meta: dict,
    seed: int,
    train_cams: list[Camera],
    train: tuple,
    heldout_rig: list[Camera],
    held: tuple | None,
) -> None:
    """out_dir/train from the shots `train` with the RECORDED cameras `train_cams` and the capture `meta`;
    out_dir/heldout (exact calibration, no stated uncertainty) when there are held-out shots."""
    _write(out_dir / "train", "cam", train_cams, train, meta)
    if held:
        exact = {k: v for k, v in meta.items() if k != "calibration_uncertainty"}
        _write(out_dir / "heldout", "orbit", heldout_rig, held, {**exact, "calibration_id": f"synthetic-seed{seed}"})


def _write(root: Path, prefix: str, cameras: Sequence[Camera], shots, meta: dict) -> None:
    images, masks, bgs = shots
    frames = [
        FrameData(f"{prefix}{i:02d}", img, cam, f"{prefix}{i:02d}", _SYNC_TIMESTAMP_NS, msk)
        for i, (cam, img, msk) in enumerate(zip(cameras, images, masks))
    ]
    write_capture(root, frames, backgrounds={f.camera_id: bg for f, bg in zip(frames, bgs)}, meta=meta)
