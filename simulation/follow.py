"""Gaussians that follow rigid bodies: each twin's splats move with its simulated pose and are
rendered with the project's rasterizer from a fixed or turntable camera.

A body at pose (R, t) moves its Gaussians by `Gaussians.transformed`: means, orientations and SH
turn with it, so view-dependent colour stays what it was in the object frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from calibration.camera import Camera, look_at_c2w
from reconstruction.gaussians import Gaussians, camera_batch, render
from reconstruction.splats import CanonicalSplats, init_splats, rgb_to_sh_dc
from simulation.scene import CameraSpec

OPAQUE_LOGIT = 4.0  # sigmoid(4) = 0.98: splats made from a bare mesh cover it like a surface


def splats_from_mesh(
    vertices: np.ndarray, faces: np.ndarray, face_rgb: np.ndarray, face_part: np.ndarray, n: int, seed: int = 0
) -> CanonicalSplats:
    """Opaque degree-0 splats on a bare mesh (no twin): area-uniform, each with its face's colour and
    part, so a CAD part can be simulated and rendered beside reconstructed twins."""
    s = init_splats(vertices, faces, n, sh_degree=0, face_part=face_part, seed=seed)
    sh = rgb_to_sh_dc(np.asarray(face_rgb)[s.face_index]).astype(np.float32)[:, None, :]
    g = s.gaussians
    return replace(s, gaussians=Gaussians(g.means, g.quats, g.log_scales, np.full(len(s), OPAQUE_LOGIT, np.float32), sh, g.eps2d))


def render_bodies(
    bodies: Sequence[Gaussians], poses: Sequence[np.ndarray], camera: Camera, background: Sequence[float] = (1.0, 1.0, 1.0)
) -> tuple[np.ndarray, np.ndarray]:
    """One image of several rigid bodies' Gaussians (each in its body frame), each moved by its pose [4, 4].

    Returns rgb [H, W, 3] float32 in [0, 1] and alpha [H, W] float32.
    """
    moved = Gaussians.concatenate([g.transformed(pose) for g, pose in zip(bodies, poses, strict=True)])
    rgb, alpha = render(moved, *camera_batch(camera), background=background)
    return rgb[0].clamp(0, 1).numpy(), alpha[0].numpy()


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


def render_trajectory(bodies: Sequence[Gaussians], poses: np.ndarray, cameras: Sequence[Camera], background=(1.0, 1.0, 1.0)) -> np.ndarray:
    """Frames uint8 [T, H, W, 3]: poses [T, B, 4, 4] of the B `bodies`."""
    frames = []
    for pose_t, cam in zip(poses, cameras, strict=True):
        rgb, _ = render_bodies(bodies, list(pose_t), cam, background)
        frames.append((rgb * 255.0 + 0.5).astype(np.uint8))
    return np.stack(frames)
