"""Deformation field: identity at init, skip at the middle, anchors interpolate, it can fit a smooth warp."""

from __future__ import annotations

import numpy as np
import pytest
import torch

torch.set_num_threads(1)  # the CI box is shared; one thread avoids oversubscription stalls

from reconstruction.deformation import (  # noqa: E402
    DeformationField,
    FieldConfig,
    farthest_point_indices,
    idw_weights,
    positional_encoding,
)


def sphere_points(n=3000, r=0.1, seed=0):
    p = np.random.default_rng(seed).normal(size=(n, 3))
    return p / np.linalg.norm(p, axis=1, keepdims=True) * r


def test_encoding_has_10_bands():
    x = torch.rand(5, 3) * 2 - 1
    e = positional_encoding(x, 10)
    assert e.shape == (5, 63)
    torch.testing.assert_close(e[:, :3], x)
    torch.testing.assert_close(e[:, 3 + 3 * 9 : 6 + 3 * 9], torch.sin(x * 512 * np.pi))


@pytest.mark.parametrize("anchors", [None, 256])
def test_field_starts_at_identity(anchors):
    pts = sphere_points()
    f = DeformationField(pts, FieldConfig(depth=8, width=64, num_anchors=anchors))
    d = f()
    assert d.shape == (3000, 3)
    assert torch.count_nonzero(d) == 0
    assert np.count_nonzero(f.offsets_at(pts[:10] * 1.5)) == 0
    # Gradients reach the network even though the output is zero.
    d.sum().backward()
    assert f.mlp.head.weight.grad.abs().sum() > 0


def test_paper_architecture_8x256_skip_at_middle():
    f = DeformationField(sphere_points(100), FieldConfig())
    layers = f.mlp.layers
    assert len(layers) == 8 and all(l.out_features == 256 for l in layers)
    assert layers[0].in_features == 63 and layers[4].in_features == 256 + 63 and layers[5].in_features == 256


def test_fps_takes_each_time_the_point_farthest_from_those_taken():
    pts = np.round(np.random.default_rng(4).normal(size=(300, 3)), 1)  # coarse grid: many ties
    idx = farthest_point_indices(pts, 40, seed=2)
    for i in range(1, len(idx)):
        d = np.min(np.sum((pts[:, None] - pts[idx[:i]][None]) ** 2, 2), 1)
        assert idx[i] == int(np.argmax(d))  # the first of equals
    assert len(farthest_point_indices(pts, 0)) == 0 and len(farthest_point_indices(pts[:3], 10)) == 3


def test_fps_spreads_and_idw_interpolates():
    pts = sphere_points(2000)
    idx = farthest_point_indices(pts, 100)
    assert len(np.unique(idx)) == 100
    a = pts[idx]
    # Farthest-point samples are well spread: min spacing far above that of a random subset.
    from scipy.spatial.distance import pdist

    rand = pts[np.random.default_rng(0).choice(2000, 100, replace=False)]
    assert pdist(a).min() > 2 * pdist(rand).min()
    nn, w = idw_weights(pts, a, 4)
    np.testing.assert_allclose(w.sum(1), 1, rtol=1e-6)
    # At an anchor the weight is all on that anchor.
    nn_a, w_a = idw_weights(a, a, 4)
    np.testing.assert_array_equal(nn_a[:, 0], np.arange(100))
    assert np.all(w_a[:, 0] > 0.999)


def fit(field, pts, target, steps=250, lr=5e-3):
    opt = torch.optim.Adam(field.mlp.parameters(), lr=lr)
    tgt = torch.tensor(target, dtype=torch.float32)
    for _ in range(steps):
        opt.zero_grad()
        loss = ((field() - tgt) ** 2).mean()
        loss.backward()
        opt.step()
    return float(np.sqrt(np.mean((field.offsets_at(pts) - target) ** 2)))


def test_fits_a_smooth_deformation_with_and_without_anchors():
    torch.manual_seed(0)
    pts = sphere_points(2000)
    # A smooth bulge: 5 mm at most on a 10 cm sphere.
    target = 0.05 * pts * np.sin(3 * pts[:, :1] / 0.1) * np.cos(2 * pts[:, 1:2] / 0.1)
    rms0 = float(np.sqrt(np.mean(target**2)))
    full = fit(DeformationField(pts, FieldConfig(depth=4, width=64, bands=4)), pts, target)
    anch = fit(DeformationField(pts, FieldConfig(depth=4, width=64, bands=4, num_anchors=512)), pts, target)
    assert full < 0.3 * rms0 and anch < 0.3 * rms0, (full, anch, rms0)


def test_offsets_scale_with_a_part_in_millimetres():
    pts = sphere_points(500, r=100.0)  # a part in millimetres
    f = DeformationField(pts, FieldConfig(depth=2, width=16, bands=3, num_anchors=64))
    with torch.no_grad():
        f.mlp.head.bias[:] = torch.tensor([0.1, 0.2, 0.3])
    assert 99.0 < float(f.radius) < 102.0
    # The head works in radius units: a bias of 0.1 is a tenth of the object's radius, in millimetres here.
    np.testing.assert_allclose(f().detach().numpy(), np.tile([0.1, 0.2, 0.3], (500, 1)) * float(f.radius), rtol=1e-5)
    assert f.num_evaluations == 64


@pytest.mark.parametrize("anchors", [None, 128])
def test_projected_field_has_no_similarity_component(anchors):
    """With project_similarity, a global translation, rotation or scaling is invisible to the field (the
    pose correction owns those), while a non-rigid warp passes through."""
    from reconstruction.deformation import similarity_basis

    pts = sphere_points(600, r=0.1)
    f = DeformationField(pts, FieldConfig(depth=2, width=16, bands=3, num_anchors=anchors, project_similarity=True))
    with torch.no_grad():
        f.mlp.head.bias[:] = torch.tensor([0.1, 0.2, 0.3])  # a pure translation of the whole field
    assert float(f().detach().abs().max()) < 1e-6
    # Random head weights: the evaluated offsets keep no least-squares similarity component.
    torch.manual_seed(0)
    with torch.no_grad():
        f.mlp.head.weight.normal_(0, 0.1)
    at = f.anchors if anchors else f.points
    d = f._mlp_at(at).detach()
    dp = f._project(d)
    basis = similarity_basis(((at - f.center) / f.radius).double())
    coef = torch.linalg.lstsq(basis, dp.double().reshape(-1, 1)).solution
    assert float(coef.abs().max()) < 1e-6 * float(d.abs().max() / f.radius)
    assert float(dp.norm()) > 0.1 * float(d.norm())  # the non-rigid part remains
    # The mesh (offsets_at) moves with the splats.
    np.testing.assert_allclose(f.offsets_at(pts), f().detach().numpy(), atol=1e-6)


def test_projection_can_keep_the_uniform_scaling():
    """On a metric rig the pose has no scale to learn: the field removes only rigid motion, so a part
    larger than its CAD model stays a deformation, while a rigid shift is still invisible."""
    from reconstruction.deformation import remove_similarity, similarity_basis

    pts = sphere_points(400, r=0.1)
    x = torch.tensor((pts - pts.mean(0)) / 0.1, dtype=torch.float64)
    rigid = similarity_basis(x, with_scale=False)
    assert rigid.shape == (3 * len(pts), 6)
    pinv = torch.linalg.pinv(rigid)
    grow = 0.03 * x  # 3 % larger about the centre
    np.testing.assert_allclose(remove_similarity(grow, rigid, pinv).numpy(), grow.numpy(), atol=1e-9)
    shift = torch.tensor([0.01, -0.02, 0.0], dtype=torch.float64).expand_as(x)
    assert float(remove_similarity(grow + shift, rigid, pinv).sub(grow).abs().max()) < 1e-9
    f = DeformationField(pts, FieldConfig(depth=2, width=16, bands=3, project_similarity=True, projection_keeps_scale=True))
    assert f.sim_basis.shape[1] == 6


def test_bfloat16_hidden_layers_match_float32_and_export():
    """Where the CPU multiplies bfloat16 natively the hidden layers run in it: the offsets stay within a fraction of
    a percent of float32, their gradients point the same way, and the export evaluates the same field as training."""
    torch.manual_seed(0)
    pts = sphere_points(3000)
    field = DeformationField(pts, FieldConfig(depth=6, width=128, bands=10, num_anchors=512))
    for p in field.mlp.parameters():
        torch.nn.init.normal_(p, std=0.05)

    def offsets_and_grads(bf16: bool):
        field.bf16 = bf16
        field.zero_grad(set_to_none=True)
        out = field()
        (out**2).sum().backward()
        return out.detach(), torch.cat([p.grad.flatten() for p in field.mlp.parameters()])

    exact, exact_grad = offsets_and_grads(False)
    fast, fast_grad = offsets_and_grads(True)
    assert float((fast - exact).norm() / exact.norm()) < 1e-2
    assert float(torch.nn.functional.cosine_similarity(fast_grad, exact_grad, 0)) > 0.999
    # The export blends the anchors' offsets as training does, with the same arithmetic.
    np.testing.assert_allclose(field.offsets_at(pts), fast.numpy(), rtol=1e-5, atol=1e-9)


def test_anchor_blend_and_its_gradient_match_the_gather():
    from reconstruction.deformation import blend_anchors

    g = torch.Generator().manual_seed(3)
    rows = torch.randn(50, 3, generator=g, requires_grad=True)
    idx = torch.randint(0, 50, (400, 4), generator=g)
    w = torch.rand(400, 4, generator=g)
    w = w / w.sum(1, keepdim=True)
    upstream = torch.randn(400, 3, generator=g)
    out = blend_anchors(rows, idx, w)
    (grad,) = torch.autograd.grad(out, rows, upstream)
    ref = torch.einsum("nk,nkd->nd", w.double(), rows.double()[idx])
    (ref_grad,) = torch.autograd.grad(ref, rows, upstream.double())
    torch.testing.assert_close(out.double(), ref, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(grad.double(), ref_grad.double(), rtol=1e-5, atol=1e-5)
