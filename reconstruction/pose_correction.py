"""Learnable camera-pose correction (paper 3.3, eq. (pose)), acting on camera-to-object poses.

`global`: one Sim(3) delta shared by all cameras of a calibrated rig, c -> s R_δ (c - p) + p + u t_δ
and R -> R_δ R, with R_δ from a 6D vector by Gram-Schmidt (Zhou et al. 2019) and s = exp(Δs); ten
parameters, identity at init. The refined registration is then ΔSim3 ∘ sim3_rig_to_object_init.
The pivot p (the object's centre) and the length unit u (its radius) condition the problem: rotating
and scaling about the object rather than the CAD origin decouples them from translation, and a
translation measured in object radii makes one learning rate mean the same for a screw and a car.

`per_camera`: the rig's Sim(3) delta as in `global`, then an SE(3) residual per camera, for rough
poses or a rig whose calibration states an extrinsic uncertainty above a pixel at the object
(`presets.choose_pose_mode`). A residual multiplies on the camera's side (c2w @ Δ), so its rotation turns
the camera about its own centre and its translation moves it along its own axes (in units u):
per-view pointing errors are then decoupled from the camera's distance to the object. The rig's
part stays what a new camera of the rig gets (`delta_sim3`); the residuals are what the training
views' calibration got wrong on its own.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from calibration.sim3 import Sim3

POSE_MODES = ("global", "per_camera")
IDENTITY_6D = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0)


def rotation_6d_to_matrix(r6: torch.Tensor) -> torch.Tensor:
    """6D vectors [..., 6] (two columns a1, a2) -> rotations [..., 3, 3] with columns b1, b2, b3 (Gram-Schmidt)."""
    a1, a2 = r6[..., :3], r6[..., 3:]
    b1 = a1 / a1.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    a2 = a2 - (b1 * a2).sum(-1, keepdim=True) * b1
    b2 = a2 / a2.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    b3 = torch.cross(b1, b2, dim=-1)
    return torch.stack([b1, b2, b3], -1)


def viewmats_from_c2w(c2w: torch.Tensor) -> torch.Tensor:
    """Rigid camera-to-world [C, 4, 4] -> world-to-camera [C, 4, 4] (differentiable, no general inverse)."""
    r = c2w[:, :3, :3]
    t = c2w[:, :3, 3:]
    rt = r.transpose(1, 2)
    top = torch.cat([rt, -rt @ t], 2)
    bottom = torch.zeros_like(c2w[:, 3:, :])
    bottom[..., 3] = 1
    return torch.cat([top, bottom], 1)


class PoseCorrection(nn.Module):
    """Corrects camera-to-object poses c2w [C, 4, 4] (OpenCV axes). Identity at initialisation.

    Parameters: the rig's Sim(3) delta `rig_r6` [1, 6], `rig_t` [1, 3], `rig_log_scale` [1] (ten
    numbers), and in `per_camera` mode the residuals `cam_r6` [C, 6], `cam_t` [C, 3].
    """

    def __init__(self, num_cameras: int, mode: str = "global", *, pivot: np.ndarray | None = None, unit: float = 1.0):
        super().__init__()
        if not unit > 0:
            raise ValueError(f"pose correction length unit must be positive, got {unit}")
        if mode not in POSE_MODES:
            raise ValueError(f"pose mode must be one of {', '.join(POSE_MODES)}, got {mode!r}")
        self.mode = mode
        self.num_cameras = num_cameras
        self.rig_r6 = nn.Parameter(torch.tensor([IDENTITY_6D], dtype=torch.float64))
        self.rig_t = nn.Parameter(torch.zeros(1, 3, dtype=torch.float64))
        self.rig_log_scale = nn.Parameter(torch.zeros(1, dtype=torch.float64))
        n = num_cameras if mode == "per_camera" else 0
        self.cam_r6 = nn.Parameter(torch.tensor([IDENTITY_6D] * n, dtype=torch.float64).reshape(n, 6))
        self.cam_t = nn.Parameter(torch.zeros(n, 3, dtype=torch.float64))
        self.register_buffer("pivot", torch.zeros(3, dtype=torch.float64) if pivot is None else torch.tensor(pivot, dtype=torch.float64))
        self.register_buffer("unit", torch.tensor(float(unit), dtype=torch.float64))

    def rig_parameters(self) -> list[nn.Parameter]:
        return [self.rig_r6, self.rig_t, self.rig_log_scale]

    def camera_parameters(self) -> list[nn.Parameter]:
        return [self.cam_r6, self.cam_t] if self.mode == "per_camera" else []

    def forward(self, c2w: torch.Tensor, index: torch.Tensor | None = None) -> torch.Tensor:
        """Corrected c2w [C, 4, 4] (float64) for cameras `index` [C] (default: all)."""
        c2w = c2w.to(torch.float64)
        rd = rotation_6d_to_matrix(self.rig_r6[0])
        r_out = rd @ c2w[:, :3, :3]
        c_out = (torch.exp(self.rig_log_scale) * (c2w[:, :3, 3] - self.pivot)) @ rd.T + self.pivot + self.unit * self.rig_t[0]
        if self.mode == "per_camera":
            sel = torch.arange(len(c2w)) if index is None else index
            c_out = c_out + self.unit * (r_out @ self.cam_t[sel, :, None])[..., 0]
            r_out = r_out @ rotation_6d_to_matrix(self.cam_r6[sel])
        out = torch.zeros_like(c2w)
        out[:, :3, :3] = r_out
        out[:, :3, 3] = c_out
        out[:, 3, 3] = 1
        return out

    @torch.no_grad()
    def reset_(self) -> None:
        """Back to the identity correction."""
        for r6 in (self.rig_r6, self.cam_r6):
            r6.copy_(torch.tensor(IDENTITY_6D, dtype=torch.float64).expand_as(r6))
        for p in (self.rig_t, self.cam_t, self.rig_log_scale):
            p.zero_()

    @torch.no_grad()
    def delta_sim3(self) -> Sim3:
        """The rig's correction as a Sim(3) in the object frame: what every camera of the rig shares."""
        r = rotation_6d_to_matrix(self.rig_r6[0]).numpy()
        s = float(torch.exp(self.rig_log_scale))
        p = self.pivot.numpy()
        return Sim3(s, r, p - s * r @ p + float(self.unit) * self.rig_t[0].numpy())


def extrinsics_error_px(uncertainty: dict, focal_px: np.ndarray, distance_m: np.ndarray) -> float:
    """The largest image displacement (px) that a calibration's stated extrinsic uncertainty
    ({"rotation_deg", "translation_mm"}) causes at the object: focal_px [C] and camera-to-object
    distance_m [C] per camera; a rotation moves the image by f * angle, a sideways shift by f * t / d."""
    rot = np.radians(float(uncertainty.get("rotation_deg") or 0.0))
    shift_m = 1e-3 * float(uncertainty.get("translation_mm") or 0.0)
    px = np.asarray(focal_px, np.float64) * (rot + shift_m / np.maximum(np.asarray(distance_m, np.float64), 1e-9))
    return float(px.max()) if px.size else 0.0
