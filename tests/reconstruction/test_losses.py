"""Losses: schedule values, SH neighbour loss, mask L1, composite, SSIM sanity."""

from __future__ import annotations

import math

import numpy as np
import torch

from reconstruction.losses import (
    composite,
    composite_parts,
    csr_matmul,
    dropout_active,
    dropout_fraction,
    mask_l1,
    neighbour_graph,
    photometric_loss,
    sh_neighbour_loss,
    silhouette_losses,
    ssim,
    support_windows,
)
from reconstruction.render import rasterize


def test_dropout_schedule_values():
    # Paper: 0.5 at the start of Stage II, cosine to 0 over 20k iterations, 0 for the last 4k.
    assert dropout_fraction(0, 20_000) == 0.5
    assert math.isclose(dropout_fraction(10_000, 20_000), 0.25)
    assert math.isclose(dropout_fraction(5_000, 20_000), 0.25 * (1 + math.cos(math.pi / 4)))
    assert dropout_fraction(20_000, 20_000) == 0.0
    assert dropout_fraction(23_999, 20_000) == 0.0
    assert dropout_fraction(0, 0) == 0.0
    vals = [dropout_fraction(s, 100) for s in range(101)]
    assert all(a >= b for a, b in zip(vals, vals[1:]))


def test_dropout_drops_exactly_without_replacement():
    g = torch.Generator().manual_seed(0)
    a = dropout_active(1000, 0.5, g)
    assert a.dtype == torch.bool and int((~a).sum()) == 500
    assert dropout_active(1000, 0.0, g) is None
    b = dropout_active(1000, 0.5, g)
    assert not torch.equal(a, b)


def test_sh_neighbour_loss_zero_for_equal_sh_and_matches_formula():
    graph = neighbour_graph(np.array([[1, 2], [0, 2], [0, 1]]))
    equal = torch.ones(3, 4, 3) * 0.7
    assert abs(float(sh_neighbour_loss(equal, graph))) < 1e-6
    sh = torch.zeros(3, 1, 3)
    sh[0, 0, 0] = 1.0
    # Pairs (0,1), (0,2), (1,0), (2,0) differ by 1: 4 / (N K = 6).
    assert math.isclose(float(sh_neighbour_loss(sh, graph)), 4 / 6, rel_tol=1e-6)


def test_neighbour_graph_skips_missing_neighbours():
    full = neighbour_graph(np.array([[1, 2], [0, 2], [0, 1]]))
    ragged = neighbour_graph(np.array([[1, -1], [0, 2], [-1, -1]]))
    assert full.num_pairs == 6 and ragged.num_pairs == 3
    sh = torch.zeros(3, 1, 3)
    sh[0, 0, 0] = 1.0
    # Listed pairs (0,1), (1,0), (1,2): two differ by 1.
    assert math.isclose(float(sh_neighbour_loss(sh, ragged)), 2 / 3, rel_tol=1e-6)


def test_sh_neighbour_loss_value_and_gradient_equal_the_pairwise_sum():
    rng = np.random.default_rng(0)
    n, k = 500, 7
    nbr = rng.integers(0, n, (n, k))  # repeated and self pairs included
    sh = torch.randn(n, 9, 3, dtype=torch.float32, requires_grad=True)
    c = sh.reshape(n, -1)
    pairwise = ((c[:, None, :] - c[torch.from_numpy(nbr)]) ** 2).sum(-1).mean()
    (g_ref,) = torch.autograd.grad(pairwise, sh)
    quadratic = sh_neighbour_loss(sh, neighbour_graph(nbr))
    (g,) = torch.autograd.grad(quadratic, sh)
    assert math.isclose(float(quadratic.detach()), float(pairwise.detach()), rel_tol=1e-5)
    torch.testing.assert_close(g, g_ref, rtol=1e-4, atol=1e-7)


def test_csr_matmul_is_scipys_product_to_the_bit():
    rng = np.random.default_rng(1)
    n = 5000  # several parts per thread
    graph = neighbour_graph(rng.integers(-1, n, (n, 9)))
    for dtype in (np.float32, np.float64):
        x = rng.standard_normal((n, 27)).astype(dtype)
        matrix = graph.laplacian.astype(dtype)
        assert np.array_equal(csr_matmul(matrix, x), matrix @ x)


def test_mask_l1_and_composite():
    alpha = torch.zeros(1, 4, 4, 1)
    mask = torch.zeros(1, 4, 4, dtype=torch.bool)
    mask[0, :2] = True
    assert math.isclose(float(mask_l1(alpha, mask)), 0.5)
    img = torch.rand(1, 4, 4, 3)
    bg = torch.tensor([0.2, 0.4, 0.6])
    out = composite(img, mask, bg)
    torch.testing.assert_close(out[0, :2], img[0, :2])
    torch.testing.assert_close(out[0, 2:], bg.expand(2, 4, 3))


def test_fill_loss_is_mean_under_coverage_inside_the_mask():
    def fill_loss(alpha, mask):
        return silhouette_losses(alpha, mask)[1]

    mask = torch.zeros(2, 4, 4)
    mask[:, 1:3, 1:3] = 1.0  # 8 object pixels over both views
    alpha = torch.full((2, 4, 4), 0.25)
    # Alpha outside the object costs nothing; inside, 1 - A averaged over the object's pixels.
    assert math.isclose(float(fill_loss(alpha, mask)), 0.75, rel_tol=1e-6)
    alpha[:, 1:3, 1:3] = 1.0
    assert float(fill_loss(alpha, mask)) == 0.0
    # Fractional (area-downsampled) coverage weights the rim pixels by how much of them is object.
    mask[0, 0, 0], alpha[0, 0, 0] = 0.5, 0.0
    assert math.isclose(float(fill_loss(alpha, mask)), 0.5 / 8.5, rel_tol=1e-6)
    assert float(fill_loss(alpha, torch.zeros(1, 4, 4))) == 0.0


def test_ssim_identity_and_photometric():
    a = torch.rand(2, 32, 32, 3)
    assert abs(float(ssim(a, a)) - 1) < 1e-5
    assert float(photometric_loss(a, a)) < 1e-5
    b = (a + 0.2 * torch.randn_like(a)).clamp(0, 1)
    assert float(ssim(a, b)) < 0.9
    l = photometric_loss(a, b)
    l1 = float((a - b).abs().mean())
    assert float(l) > 0.8 * l1


def test_support_windows_cover_the_support_with_a_margin_inside_the_image():
    support = torch.zeros(3, 40, 50, dtype=torch.bool)
    support[0, 10:15, 20:30] = True
    support[1, 0:3, 45:50] = True  # at a corner: the window slides back inside
    corners, h, w = support_windows(support, 4)
    assert (h, w) == (13, 18)
    for v in range(2):
        ys, xs = torch.nonzero(support[v], as_tuple=True)
        y0, x0 = corners[v].tolist()
        assert y0 <= int(ys.min()) and int(ys.max()) < y0 + h and x0 <= int(xs.min()) and int(xs.max()) < x0 + w
        assert 0 <= y0 <= 40 - h and 0 <= x0 <= 50 - w
    assert corners[2].tolist() == [0, 0]  # nothing to cover


def test_windowed_photometric_loss_equals_the_whole_image_loss_and_its_gradient():
    """A rasterized object composited on the target's background: the loss over the windows around
    the splats and the mask has the whole image's value and gradient."""
    torch.manual_seed(0)
    n, v, w, h = 60, 2, 96, 72
    means = (torch.rand(n, 3) - 0.5) * torch.tensor([0.3, 0.3, 0.0]) + torch.tensor([0.0, 0.0, 3.0])
    means.requires_grad_(True)
    quats = torch.nn.functional.normalize(torch.randn(n, 4), dim=1)
    scales = torch.full((n, 3), 0.03)
    opac = torch.full((n,), 0.8)
    colors = torch.rand(n, 3, requires_grad=True)
    viewmats = torch.eye(4).repeat(v, 1, 1)
    viewmats[1, 0, 3] = 0.2
    ks = torch.tensor([[80.0, 0, 40], [0, 80.0, 30], [0, 0, 1]]).repeat(v, 1, 1)
    bg = torch.rand(v, 3)
    mask = torch.zeros(v, h, w)
    mask[:, 25:40, 30:50] = 1.0
    target = composite(torch.rand(v, h, w, 3), mask, bg)
    rgb, alpha, _ = rasterize(means, quats, scales, opac, colors, viewmats, ks, w, h, backgrounds=bg)
    support = (alpha.detach()[..., 0] > 0) | (mask > 0)
    assert support.float().mean() < 0.5  # the window is a real crop
    whole = photometric_loss(rgb, target)
    windowed = photometric_loss(rgb, target, support=support)
    g_whole = torch.autograd.grad(whole, (means, colors), retain_graph=True)
    g_window = torch.autograd.grad(windowed, (means, colors))
    assert math.isclose(float(windowed.detach()), float(whole.detach()), rel_tol=1e-5)
    for a, b in zip(g_window, g_whole):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-8)


def test_pixels_beyond_a_photo_pull_on_nothing():
    """A portrait photo on a landscape-wide canvas: a splat seen only beyond the photo's edge gets no
    gradient from the mask or the photometric loss, and L_mask is the photo's own mean."""
    torch.manual_seed(0)
    w, h, photo_w = 96, 72, 48
    means = torch.tensor([[-0.1, 0.0, 3.0], [0.4, 0.0, 3.0]], requires_grad=True)  # left on the photo, right beyond it
    quats = torch.tensor([[1.0, 0, 0, 0]]).repeat(2, 1)
    scales = torch.full((2, 3), 0.03)
    opac = torch.full((2,), 0.8)
    colors = torch.rand(2, 3, requires_grad=True)
    ks = torch.tensor([[[80.0, 0, 48], [0, 80.0, 36], [0, 0, 1]]])
    bg = torch.rand(1, 3)
    mask = torch.zeros(1, h, w)
    mask[:, 30:42, 30:44] = 1.0
    valid = torch.zeros(1, h, w, dtype=torch.bool)
    valid[:, :, :photo_w] = True
    target = composite(torch.rand(1, h, w, 3), mask, bg)
    rgb, alpha, _ = rasterize(means, quats, scales, opac, colors, torch.eye(4)[None], ks, w, h, backgrounds=bg)
    assert alpha[0, :, photo_w:].sum() > 1 and alpha[0, :, :photo_w].sum() > 1
    support = (alpha.detach()[..., 0] > 0) | (mask > 0)
    for loss in (
        mask_l1(alpha, mask, valid),
        photometric_loss(rgb, target, support=support, valid=valid),
        photometric_loss(rgb, target, valid=valid),
    ):
        g_means, g_colors = torch.autograd.grad(loss, (means, colors), retain_graph=True)
        assert g_means[1].abs().max() == 0 and g_colors[1].abs().max() == 0
        assert g_means[0].abs().max() > 0  # the splat on the photo still learns
    g_means, _ = torch.autograd.grad(mask_l1(alpha, mask), (means, colors), retain_graph=True)
    assert g_means[1].abs().max() > 0  # without `valid` the canvas beyond the photo pushes the splat away
    photo = (slice(None), slice(None), slice(0, photo_w))
    assert math.isclose(float(mask_l1(alpha, mask, valid).detach()), float(mask_l1(alpha[photo], mask[photo]).detach()), rel_tol=1e-6)


def test_composite_parts_give_the_composite_over_any_background():
    gen = torch.Generator().manual_seed(5)
    image, mask = torch.rand(2, 6, 7, 3, generator=gen), torch.rand(2, 6, 7, generator=gen)
    fg, bg_weight = composite_parts(image, mask)
    for background in (torch.rand(2, 3, generator=gen), torch.zeros(2, 3)):
        assert torch.allclose(fg + background[:, None, None, :] * bg_weight, composite(image, mask, background), atol=1e-7)


def test_fused_silhouette_losses_match_their_formulas_and_gradients():
    # The float32 CPU path (one numba pass each way) against the same losses as torch ops in float64.
    g = torch.Generator().manual_seed(3)
    alpha = torch.rand(3, 20, 30, 1, generator=g)
    alpha[0, :5] = 0.0  # ties |A - M| = 0 where the mask is 0 too: no gradient there, as torch's abs
    mask = (torch.rand(3, 20, 30, generator=g) > 0.6).float() * torch.rand(3, 20, 30, generator=g).clamp_min(0.5)
    mask[0, :5] = 0.0
    valid = torch.rand(3, 20, 30, generator=g) > 0.2
    for v in (None, valid):
        fast = alpha.clone().requires_grad_(True)
        l_mask, l_fill = silhouette_losses(fast, mask, v)
        (0.7 * l_mask + 0.3 * l_fill).backward()
        ref = alpha.double().requires_grad_(True)
        r_mask, r_fill = silhouette_losses(ref, mask, v)
        (0.7 * r_mask + 0.3 * r_fill).backward()
        assert l_mask.dtype == torch.float32 and fast.grad.shape == alpha.shape
        assert math.isclose(l_mask.item(), r_mask.item(), rel_tol=1e-6)
        assert math.isclose(l_fill.item(), r_fill.item(), rel_tol=1e-6)
        torch.testing.assert_close(fast.grad.double(), ref.grad, rtol=1e-6, atol=1e-9)
