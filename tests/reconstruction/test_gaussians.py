"""The one Gaussian-set type and the one render: moving the Gaussians equals moving the camera back
(means, orientations, scale and view-dependent colour), activation keeps gradients, bad shapes refused."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from calibration.camera import Camera, look_at_c2w
from calibration.sim3 import Sim3
from reconstruction.gaussians import EPS2D_3DGS, Gaussians, camera_batch, render, sh_rotation, straight_rgba
from reconstruction.render import rasterize


def random_gaussians(n: int = 400, degree: int = 3, seed: int = 0) -> Gaussians:
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2
    return Gaussians.from_arrays(
        rng.normal(size=(n, 3)) * 0.05,
        rng.normal(size=(n, 4)),
        rng.normal(size=(n, 3)) * 0.2 - 4.0,
        rng.normal(size=n),
        rng.normal(size=(n, k, 3)) * 0.4,
    )


def camera() -> Camera:
    return Camera.from_fov(np.deg2rad(50), 64, 48, look_at_c2w(np.array([0.3, 0.1, 0.15]), np.zeros(3)))


@pytest.mark.parametrize("scale", [1.0, 1.7])
def test_moving_the_gaussians_equals_moving_the_camera_back(scale):
    g = random_gaussians()
    move = Sim3(scale, Rotation.from_rotvec([0.4, -0.7, 1.1]).as_matrix(), np.array([0.03, -0.02, 0.05]))
    cam = camera()
    moved = render(g.transformed(move), *camera_batch(cam))
    back = render(g, *camera_batch(cam.with_c2w(move.inverse().apply_to_c2w(cam.c2w))))
    assert float(moved[1].mean()) > 0.05  # the Gaussians are in view
    for a, b in zip(moved, back):
        assert float((a - b).abs().max()) < 1e-5
    unmoved = render(g, *camera_batch(cam))
    assert float((moved[0] - unmoved[0]).abs().mean()) > 0.01


def test_sh_rotation_is_a_representation():
    r1, r2 = Rotation.random(2, random_state=3).as_matrix()
    for degree in range(4):
        np.testing.assert_allclose(sh_rotation(r1 @ r2, degree), sh_rotation(r1, degree) @ sh_rotation(r2, degree), atol=1e-10)
    np.testing.assert_allclose(sh_rotation(np.eye(3), 3), np.eye(16), atol=1e-12)


def test_activation_keeps_gradients_and_never_writes_back():
    g = random_gaussians(n=50, degree=1)
    log_scales = torch.tensor(np.asarray(g.log_scales), requires_grad=True)
    trained = Gaussians(
        torch.as_tensor(g.means), torch.as_tensor(g.quats), log_scales, torch.as_tensor(g.opacity_logits), torch.as_tensor(g.sh)
    )
    rgb, alpha = render(trained, *camera_batch(camera()))
    alpha.sum().backward()
    assert log_scales.grad is not None and float(log_scales.grad.abs().sum()) > 0
    before = np.asarray(g.opacity_logits).copy()
    g.activated()[3].mul_(0)
    np.testing.assert_array_equal(g.opacity_logits, before)


def test_straight_alpha_undoes_the_premultiplied_render():
    g = random_gaussians(n=200, degree=0)
    over_black = render(g, *camera_batch(camera()), background=None)
    over_white = render(g, *camera_batch(camera()), background=(1.0, 1.0, 1.0))
    rgba = straight_rgba(*over_black)[0]
    composite = rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:])
    np.testing.assert_allclose(composite, np.clip(over_white[0][0].numpy(), 0, 1), atol=1e-4)


def test_subset_concatenate_and_degree_padding():
    a, b = random_gaussians(n=30, degree=0), random_gaussians(n=20, degree=2, seed=1)
    both = Gaussians.concatenate([a, b])
    assert len(both) == 50 and both.sh_degree == 2
    np.testing.assert_array_equal(both.sh[:30, 1:], 0)
    np.testing.assert_array_equal(both.subset(np.arange(30, 50)).sh, b.sh)


def test_bad_shapes_are_refused():
    g = random_gaussians(n=10, degree=1)
    with pytest.raises(ValueError, match="quats has shape"):
        Gaussians(g.means, g.quats[:, :3], g.log_scales, g.opacity_logits, g.sh)
    with pytest.raises(ValueError, match="degree"):
        Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, np.zeros((10, 5, 3), np.float32))
    with pytest.raises(ValueError, match="share an image size"):
        camera_batch([camera(), Camera.from_fov(1.0, 32, 32)])


def test_a_set_is_drawn_with_the_dilation_it_was_fitted_with():
    g = random_gaussians(n=200, degree=1)
    sharp = replace(g, eps2d=0.1)
    cams = camera_batch(camera())
    _, alpha_3dgs = render(g, *cams)
    _, alpha_sharp = render(sharp, *cams)
    assert g.eps2d == EPS2D_3DGS == 0.3
    # Less dilation draws each splat smaller: less coverage, and a different image.
    assert float(alpha_sharp.sum()) < float(alpha_3dgs.sum())
    # Every derived set keeps it, so a twin moved, cut or padded still draws what was fitted.
    for derived in (
        sharp.subset(np.arange(50)),
        sharp.with_sh_degree(3),
        sharp.transformed(Sim3.identity()),
        Gaussians.from_arrays(sharp.means, sharp.quats, sharp.log_scales, sharp.opacity_logits, sharp.sh, sharp.eps2d),
    ):
        assert derived.eps2d == 0.1
    assert Gaussians.concatenate([sharp, g]).eps2d == 0.1
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="eps2d"):
            replace(g, eps2d=bad)
        with pytest.raises(ValueError, match="eps2d"):
            rasterize(*g.activated(), *cams[:2], 64, 48, sh_degree=g.sh_degree, eps2d=bad)
