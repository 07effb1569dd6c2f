"""Near-symmetries of a surface: found on shapes whose symmetries are known, absent on an asymmetric one."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from reconstruction.pose_metrics import registration_errors
from reconstruction.symmetry import near_symmetries, rotation_about

FAST = {"samples": 6000, "queries": 600}


def _mesh(m: trimesh.Trimesh, transform: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    if transform is not None:
        m = m.copy()
        m.apply_transform(transform)
    return np.asarray(m.vertices), np.asarray(m.faces)


def _pose(deg: float, axis, offset) -> np.ndarray:
    T = rotation_about(np.asarray(axis, float), np.radians(deg), np.zeros(3))
    T[:3, 3] = offset
    return T


def _rotations(syms) -> np.ndarray:
    return np.stack([s.transform[:3, :3] for s in syms])


def test_box_with_three_side_lengths_has_exactly_its_three_half_turns() -> None:
    pose = _pose(30.0, [1.0, 2.0, 0.5], [0.2, -0.1, 0.05])  # off the origin and turned: axes come from the surface
    v, f = _mesh(trimesh.creation.box(extents=[0.04, 0.08, 0.12]), pose)
    syms = near_symmetries(v, f, tolerance=0.003, **FAST)
    assert len(syms) == 3 and all(not s.continuous for s in syms)
    np.testing.assert_allclose([s.angle_deg for s in syms], 180.0, atol=1.0)
    # Each is a half-turn about one of the box's own axes, through its centre.
    axes = pose[:3, :3].T
    for s in syms:
        assert max(abs(float(s.axis @ a)) for a in axes) > 0.999
        np.testing.assert_allclose(s.transform[:3, :3] @ pose[:3, 3] + s.transform[:3, 3], pose[:3, 3], atol=1e-3)


def test_cylinder_is_continuous_about_its_axis_and_flips_end_over_end() -> None:
    v, f = _mesh(trimesh.creation.cylinder(radius=0.02, height=0.15, sections=64), _pose(20.0, [0, 1, 0], [0, 0, 0.1]))
    syms = near_symmetries(v, f, tolerance=0.003, continuous_step_deg=5.0, **FAST)
    continuous = [s for s in syms if s.continuous]
    spin = [
        s for s in continuous if s.angle_deg < 179.0 and abs(float(s.axis @ [np.sin(np.radians(20)), 0, np.cos(np.radians(20))])) > 0.999
    ]
    assert len(spin) >= 60  # 5-degree samples of the turn about the long axis
    # The end-over-end flip is there too (a half-turn about an axis across the cylinder).
    across = [s for s in syms if not s.continuous and s.angle_deg > 179.0]
    assert across


def test_asymmetric_part_has_none() -> None:
    body = trimesh.creation.box(extents=[0.06, 0.04, 0.02])
    arm = trimesh.creation.box(extents=[0.02, 0.05, 0.02])
    arm.apply_translation([0.03, 0.035, 0.015])
    knob = trimesh.creation.icosphere(subdivisions=2, radius=0.012)
    knob.apply_translation([-0.025, -0.01, -0.015])
    v, f = _mesh(trimesh.util.concatenate([body, arm, knob]))
    assert near_symmetries(v, f, tolerance=0.003, **FAST) == []


def test_registration_is_not_charged_for_a_turn_about_the_centroid() -> None:
    """A box away from the origin, registered turned 180 deg about its own centre: zero error modulo the
    found symmetries, a large one without them (the turn moves every camera)."""
    pose = _pose(0.0, [0, 0, 1], [0.3, 0.1, 0.0])
    v, f = _mesh(trimesh.creation.box(extents=[0.04, 0.08, 0.12]), pose)
    syms = near_symmetries(v, f, tolerance=0.003, **FAST)
    turn = rotation_about(np.array([0.0, 0.0, 1.0]), np.pi, pose[:3, 3])
    gt = np.stack([np.linalg.inv(_pose(a, [0, 1, 0], [np.sin(np.radians(a)), 0.2, np.cos(np.radians(a))])) for a in (0, 70, 140, 210)])
    est = gt @ np.linalg.inv(turn)  # the cameras see the object turned by `turn`
    assert registration_errors(est, gt)["rotation_deg_median"] == pytest.approx(180.0)
    r = registration_errors(est, gt, symmetries=[s.transform for s in syms])
    assert r["rotation_deg_median"] < 0.5 and r["center_pct_median"] < 0.5


def test_tolerance_must_be_positive() -> None:
    v, f = _mesh(trimesh.creation.box())
    with pytest.raises(ValueError, match="tolerance"):
        near_symmetries(v, f, tolerance=0.0)
