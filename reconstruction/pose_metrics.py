"""Registration errors of the evaluation protocol: rotation (deg) and camera-centre (% of distance).

Poses are world-to-camera `viewmat`s [N, 4, 4] (OpenCV axes, SPEC conventions) with the world being
the object's canonical frame, for the estimated and the ground-truth cameras alike. Computed in
float64; torch tensors and numpy arrays are both accepted. The rotation error is
`calibration.so3.geodesic_angle_deg`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TypedDict

import numpy as np
import torch

from calibration.so3 import geodesic_angle_deg

Array = np.ndarray | torch.Tensor


class RegistrationErrors(TypedDict):
    rotation_deg: np.ndarray  # [N] geodesic rotation error per camera, degrees
    center_pct: np.ndarray  # [N] camera-centre error per camera, % of camera-to-object distance
    rotation_deg_median: float
    center_pct_median: float
    symmetry: int | None  # index of the chosen symmetry, None for the identity


def _numpy(x: Array) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def camera_centers(viewmats: Array) -> np.ndarray:
    """Camera centres [N, 3] in the world frame of world-to-camera `viewmats` [N, 4, 4]: c = -R^T t."""
    v = _numpy(viewmats)
    return -np.einsum("nji,nj->ni", v[:, :3, :3], v[:, :3, 3])


def center_error_pct(c_est: Array, c_gt: Array, object_center: Array | None = None) -> np.ndarray:
    """Distance between camera centres `c_est` and `c_gt` [N, 3] as a percentage of the GT camera's
    distance to `object_center` [3] (default: the object frame's origin); returns [N]."""
    c_est, c_gt = _numpy(c_est), _numpy(c_gt)
    o = np.zeros(3) if object_center is None else _numpy(object_center)
    return 100.0 * np.linalg.norm(c_est - c_gt, axis=-1) / np.linalg.norm(c_gt - o, axis=-1)


def _rigid(S: Array) -> np.ndarray:
    """A symmetry as a [4, 4] transform; a [3, 3] rotation is taken about the origin."""
    S = _numpy(S)
    if S.shape == (4, 4):
        return S
    if S.shape != (3, 3):
        raise ValueError(f"a symmetry must be a [3, 3] rotation or a [4, 4] transform, got shape {S.shape}")
    T = np.eye(4)
    T[:3, :3] = S
    return T


def registration_errors(
    viewmats_est: Array,
    viewmats_gt: Array,
    symmetries: Sequence[Array] | None = None,
    object_center: Array | None = None,
) -> RegistrationErrors:
    """Per-camera and median registration errors of estimated cameras against ground truth.

    Args:
        viewmats_est: [N, 4, 4] estimated world(object)-to-camera matrices.
        viewmats_gt: [N, 4, 4] ground-truth ones, same cameras in the same order.
        symmetries: optional transforms S that map the object onto itself (x -> S x in the object
            frame): rotations about the origin [3, 3] or rigid transforms [4, 4] (e.g. a turn about
            the object's centroid). An estimate V is then as right as V S, whose centre is S^-1 c.
            The identity is always included. One S is chosen for the whole capture, the one with
            the lowest median rotation error: a registration places the object once for all
            cameras, so letting each camera pick its own S would hide a wrong registration.
        object_center: [3] point the camera distances are measured to (default: origin).

    Returns:
        Per-camera errors (float64 [N]), their medians, and the chosen symmetry's index.
    """
    est, gt = _numpy(viewmats_est), _numpy(viewmats_gt)
    if est.shape != gt.shape or est.shape[-2:] != (4, 4) or est.ndim != 3:
        raise ValueError(f"expected two [N, 4, 4] viewmat stacks, got {est.shape} and {gt.shape}")
    c_gt = camera_centers(gt)
    results: list[RegistrationErrors] = []
    for index, S in enumerate([np.eye(4), *(_rigid(S) for S in symmetries or ())]):
        moved = est @ S
        rot = geodesic_angle_deg(gt[:, :3, :3], moved[:, :3, :3])
        ctr = center_error_pct(camera_centers(moved), c_gt, object_center)
        results.append(
            RegistrationErrors(
                rotation_deg=rot,
                center_pct=ctr,
                rotation_deg_median=float(np.median(rot)),
                center_pct_median=float(np.median(ctr)),
                symmetry=index - 1 if index else None,
            )
        )
    # min() keeps the first of equals, so the identity wins ties.
    return min(results, key=lambda r: r["rotation_deg_median"])
