"""Photo-consistency: exact samples at pixel centres, a robust spread that ignores single views, and a
minimum at the true pose of a textured surface seen by several cameras."""

from __future__ import annotations

import numpy as np
import torch

from calibration.camera import look_at_c2w
from calibration.so3 import axis_angle_to_matrix
from reconstruction.photo_consistency import blurred, consistency_loss, sample_colors

W, H, F = 96, 72, 90.0
K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]])


def texture(xy: np.ndarray) -> np.ndarray:
    """A smooth colour pattern [N, 3] on the plane z = 0."""
    x, y = xy[:, 0], xy[:, 1]
    return np.stack([0.5 + 0.3 * np.sin(40 * x) * np.cos(25 * y), 0.5 + 0.3 * np.cos(30 * x + 10 * y), 0.5 + 0.2 * np.sin(35 * y)], 1)


def render_plane(c2w: np.ndarray) -> np.ndarray:
    """The textured plane z = 0 seen by a pinhole camera c2w (OpenCV): image [H, W, 3]."""
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    rays = np.stack([(u - K[0, 2]) / F, (v - K[1, 2]) / F, np.ones_like(u)], -1).reshape(-1, 3) @ c2w[:3, :3].T
    o = c2w[:3, 3]
    t = -o[2] / rays[:, 2]
    return texture(o[:2] + t[:, None] * rays[:, :2]).reshape(H, W, 3).astype(np.float32)


def cameras() -> np.ndarray:
    return np.stack([look_at_c2w(np.array([0.25 * np.cos(a), 0.25 * np.sin(a), 0.4]), np.zeros(3)) for a in (0.3, 2.4, 4.4)])


def test_samples_at_pixel_centres_are_the_pixels():
    img = torch.rand(1, H, W, 3)
    c2w = np.eye(4)
    # Points at depth 1 projecting exactly onto pixel centres (u, v) = (10.5, 20.5) and (50.5, 3.5).
    uv = np.array([[10.5, 20.5], [50.5, 3.5]])
    pts = np.concatenate([(uv - K[:2, 2]) / F, np.ones((2, 1))], 1)
    out = sample_colors(
        img,
        torch.tensor(pts, dtype=torch.float32),
        torch.tensor(np.linalg.inv(c2w), dtype=torch.float32)[None],
        torch.tensor(K, dtype=torch.float32)[None],
    )
    np.testing.assert_allclose(out[0].numpy(), img[0, [20, 3], [10, 50]].numpy(), atol=1e-6)


def test_spread_is_zero_when_views_agree_and_ignores_points_seen_once():
    colors = torch.rand(1, 5, 3).expand(3, 5, 3).clone()
    weights = torch.ones(3, 5)
    assert float(consistency_loss(colors, weights)) == 0.0
    colors[0, 2] += 0.5
    assert float(consistency_loss(colors, weights)) > 0.0
    # The disagreeing view no longer sees point 2, and point 4 is seen by one view only.
    weights[0, 2] = 0
    weights[1:, 4] = 0
    colors[0, 4] += 0.9
    assert float(consistency_loss(colors, weights)) == 0.0


def test_true_pose_is_the_minimum_and_the_gradient_points_back():
    c2w = cameras()
    images = blurred(torch.tensor(np.stack([render_plane(c) for c in c2w])), 1.0)
    rng = np.random.default_rng(0)
    pts = np.concatenate([rng.uniform(-0.08, 0.08, (2000, 2)), np.zeros((2000, 1))], 1)
    ks = torch.tensor(np.stack([K] * len(c2w)), dtype=torch.float32)
    weights = torch.ones(len(c2w), len(pts))

    def loss_for(shift: np.ndarray, turn: np.ndarray) -> torch.Tensor:
        # The surface moved off the truth by a rigid motion: points carried by (turn, shift).
        moved = pts @ axis_angle_to_matrix(turn).T + shift
        p = torch.tensor(moved, dtype=torch.float32, requires_grad=True)
        viewmats = torch.tensor(np.linalg.inv(c2w), dtype=torch.float32)
        value = consistency_loss(sample_colors(images, p, viewmats, ks), weights)
        value.backward()
        return value.detach(), p.grad

    at_truth, _ = loss_for(np.zeros(3), np.zeros(3))
    for shift, turn in ((np.array([0, 0, 0.004]), np.zeros(3)), (np.zeros(3), np.array([0.03, -0.02, 0.0]))):
        off, grad = loss_for(shift, turn)
        assert float(off) > 2 * float(at_truth)
    # Lifted off the plane, the points are pulled back down: the mean z-gradient opposes the lift.
    _, grad = loss_for(np.array([0, 0, 0.004]), np.zeros(3))
    assert float(grad[:, 2].sum()) > 0


def test_fused_spread_equals_the_formula_and_its_gradient():
    # The CPU kernel against the loss written out in torch ops (the form kept for GPU tensors).
    def formula(colors, weights, eps=0.05):
        wsum = weights.sum(0)
        used = (wsum >= 2).to(colors.dtype)
        mean = (weights[..., None] * colors).sum(0) / wsum.clamp_min(1)[:, None]
        rho = eps * eps * (torch.sqrt(1 + ((colors - mean[None]) ** 2).sum(-1) / (eps * eps)) - 1)
        return (weights * used[None] * rho).sum() / (weights * used[None]).sum().clamp_min(1)

    gen = torch.Generator().manual_seed(3)
    colors = torch.rand(6, 3000, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    weights = (torch.rand(6, 3000, generator=gen) > 0.6).double() * torch.rand(6, 3000, generator=gen, dtype=torch.float64) * 2
    weights[:, :50] = 0.0
    weights[0, 50:60] = 1.0  # seen by one view only
    fused, ref = consistency_loss(colors, weights), formula(colors, weights)
    (g_fused,), (g_ref,) = torch.autograd.grad(fused, colors), torch.autograd.grad(ref, colors)
    assert torch.allclose(fused, ref, rtol=1e-12, atol=0)
    assert torch.allclose(g_fused, g_ref, rtol=1e-9, atol=1e-18)
    assert float(consistency_loss(colors[:, :50], weights[:, :50]).detach()) == 0.0


def test_fused_sampler_equals_grid_sample_and_its_gradients():
    # The CPU kernel against the torch form (projection, grid_sample), which the images requiring grad select:
    # samples inside, on the border and off the image, for the points and the poses.
    gen = torch.Generator().manual_seed(5)
    images = torch.rand(3, H, W, 3, generator=gen, dtype=torch.float64)
    c2w = cameras()
    viewmats = torch.tensor(np.linalg.inv(c2w), requires_grad=True)
    ks = torch.tensor(np.stack([K] * 3))

    def run(imgs, pts):
        pts = pts.clone().requires_grad_(True)
        out = sample_colors(imgs, pts, viewmats, ks)
        upstream = torch.randn(out.shape, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
        return (out, *torch.autograd.grad(out, (pts, viewmats), upstream))

    pts = torch.cat(
        [
            torch.rand(500, 3, generator=gen, dtype=torch.float64) * 0.3 - 0.15,
            torch.tensor([[5.0, 0.0, 0.0], [0.0, -4.0, 0.1]], dtype=torch.float64),
        ]
    )
    for got, want in zip(run(images, pts), run(images.clone().requires_grad_(True), pts)):
        torch.testing.assert_close(got, want, rtol=1e-7, atol=1e-9)
    # Behind the cameras: the border's colour, and no gradient (torch's form divides by the clamped depth there).
    behind = torch.tensor([[0.0, 0.0, 0.6]], dtype=torch.float64)
    out, v_points, v_viewmats = run(images, behind)
    torch.testing.assert_close(out, run(images.clone().requires_grad_(True), behind)[0])
    assert not v_points.any() and not v_viewmats.any()
