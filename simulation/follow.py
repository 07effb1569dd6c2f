"""Gaussians that follow rigid bodies: each twin's splats move with its simulated pose and are
rendered with the project's rasterizer from a fixed or turntable camera.

A body at pose (R, t) moves a splat to mean' = R mean + t, quat' = q_R (x) quat. View-dependent
colour stays exact: the SH were fitted in the object frame, so they are evaluated along the view
direction rotated back into it, R^T (mean' - camera centre).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from calibration.camera import Camera, look_at_c2w
from calibration.so3 import matrix_to_quat, quat_multiply
from reconstruction.splats import init_splats, rgb_to_sh_dc
from reconstruction.twin import Twin
from simulation.scene import CameraSpec

OPAQUE_LOGIT = 4.0  # sigmoid(4) = 0.98: splats made from a bare mesh cover it like a surface


def transform_splats(means: np.ndarray, quats: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Splat means [N, 3] and quats [N, 4] wxyz moved rigidly by pose [4, 4] (object-to-world)."""
    r, t = np.asarray(pose[:3, :3], np.float64), np.asarray(pose[:3, 3], np.float64)
    means_w = np.asarray(means, np.float64) @ r.T + t
    quats_w = quat_multiply(matrix_to_quat(r)[None], quats)
    return means_w, quats_w


def splats_from_twin(twin: Twin) -> dict[str, np.ndarray]:
    """The twin's splat arrays (object frame) as `render_bodies` takes them."""
    return {
        "means": twin.means, "quats": twin.quats, "log_scales": twin.log_scales, "opacity_logits": twin.opacity_logits,
        "sh": twin.sh, "sh_degree": int(twin.sh_degree), "part_label": twin.part_label,
    }


def splats_from_mesh(vertices: np.ndarray, faces: np.ndarray, face_rgb: np.ndarray, face_part: np.ndarray, n: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Opaque degree-0 splats on a bare mesh (no twin): area-uniform, each with its face's colour and
    part, so a CAD part can be simulated and rendered beside reconstructed twins."""
    s = init_splats(vertices, faces, n, sh_degree=0, face_part=face_part, seed=seed)
    sh = rgb_to_sh_dc(np.asarray(face_rgb)[s.face_index]).astype(np.float32)[:, None, :]
    return {
        "means": s.means, "quats": s.quats, "log_scales": s.log_scales, "opacity_logits": np.full(len(s), OPAQUE_LOGIT, np.float32),
        "sh": sh, "sh_degree": 0, "part_label": s.part_label,
    }


def view_colors(sh: np.ndarray, sh_degree: int, means_world: np.ndarray, rotation: np.ndarray, camera_center: np.ndarray) -> np.ndarray:
    """RGB [N, 3] of splats seen from `camera_center`, with SH [N, K, 3] evaluated in the object
    frame (rotation [3, 3] object-to-world), as the rasterizer would: max(SH(dir) + 0.5, 0)."""
    import torch

    from reconstruction.render import eval_sh

    dirs_obj = (np.asarray(means_world, np.float64) - np.asarray(camera_center)) @ np.asarray(rotation)
    with torch.no_grad():
        rgb = eval_sh(int(sh_degree), torch.as_tensor(np.asarray(sh, np.float32)), torch.as_tensor(dirs_obj, dtype=torch.float32))
    return np.maximum(rgb.numpy() + 0.5, 0.0)


def render_bodies(
    splat_sets: Sequence[dict], poses: Sequence[np.ndarray], camera: Camera, background: Sequence[float] = (1.0, 1.0, 1.0)
) -> tuple[np.ndarray, np.ndarray]:
    """One image of several rigid bodies' splats, each moved by its pose [4, 4].

    Returns rgb [H, W, 3] float32 in [0, 1] and alpha [H, W] float32.
    """
    import torch

    from reconstruction.render import rasterize

    means, quats, scales, opac, cols = [], [], [], [], []
    for s, pose in zip(splat_sets, poses, strict=True):
        m, q = transform_splats(s["means"], s["quats"], pose)
        means.append(m)
        quats.append(q)
        scales.append(np.exp(np.asarray(s["log_scales"], np.float64)))
        opac.append(1.0 / (1.0 + np.exp(-np.asarray(s["opacity_logits"], np.float64))))
        cols.append(view_colors(s["sh"], s["sh_degree"], m, pose[:3, :3], camera.center))
    f32 = lambda parts: torch.as_tensor(np.concatenate(parts), dtype=torch.float32)  # noqa: E731
    with torch.no_grad():
        rgb, alpha, _ = rasterize(
            f32(means), f32(quats), f32(scales), f32(opac), f32(cols),
            torch.as_tensor(camera.viewmat[None], dtype=torch.float32), torch.as_tensor(camera.K[None], dtype=torch.float32),
            camera.width, camera.height, backgrounds=torch.tensor([list(background)], dtype=torch.float32),
        )
    return rgb[0].clamp(0, 1).numpy(), alpha[0, ..., 0].numpy()


def camera_path(spec: CameraSpec, n_frames: int) -> list[Camera]:
    """Render cameras for `n_frames`: the same look-at camera, or a turntable orbiting `target`
    about the world z axis by `spec.turns` revolutions from the first frame to the last."""
    eye, target = np.asarray(spec.eye, np.float64), np.asarray(spec.target, np.float64)
    cams = []
    for f in range(n_frames):
        angle = 0.0 if spec.mode == "fixed" or n_frames < 2 else 2 * np.pi * spec.turns * f / (n_frames - 1)
        c, s = np.cos(angle), np.sin(angle)
        rel = eye - target
        e = target + np.array([c * rel[0] - s * rel[1], s * rel[0] + c * rel[1], rel[2]])
        cams.append(Camera.from_fov(np.deg2rad(spec.fov_deg), spec.width, spec.height, look_at_c2w(e, target, np.asarray(spec.up))))
    return cams


def render_trajectory(splat_sets: Sequence[dict], poses: np.ndarray, cameras: Sequence[Camera], background=(1.0, 1.0, 1.0)) -> np.ndarray:
    """Frames uint8 [T, H, W, 3]: poses [T, B, 4, 4] of the B bodies whose splats are `splat_sets`."""
    frames = []
    for pose_t, cam in zip(poses, cameras, strict=True):
        rgb, _ = render_bodies(splat_sets, list(pose_t), cam, background)
        frames.append((rgb * 255.0 + 0.5).astype(np.uint8))
    return np.stack(frames)
