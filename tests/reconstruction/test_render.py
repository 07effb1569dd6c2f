"""The CPU rasterizer against a dense per-pixel PyTorch reference written here (float64, autograd).

The reference shares no code with `reconstruction.render`: it builds rotations by rotating basis
vectors with the quaternion, inverts the 2D covariance with `torch.linalg.inv`, evaluates every
Gaussian at every pixel and composites with a cumulative product. The rasterizer runs on float32
inputs, as in production; the reference runs on the same values cast to float64.
"""

from __future__ import annotations

import math
import os
import select
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from numba import njit

from reconstruction.render import _cpu_kernels as kernels
from reconstruction.render import eval_sh, num_sh_bases, project_gaussians, rasterize
from reconstruction.render.sh import sh_colors

PARAMS = ("means", "quats", "scales", "opacities", "colors", "viewmats", "backgrounds")


# --------------------------------------------------------------------------- reference


def _ref_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """[N, 3, 3] by rotating e_x, e_y, e_z: v' = v + 2 w (u x v) + 2 u x (u x v), u = (x, y, z)."""
    q = quats / quats.norm(dim=-1, keepdim=True)
    w, u = q[:, :1], q[:, 1:]
    cols = []
    for axis in range(3):
        v = torch.zeros_like(u)
        v[:, axis] = 1.0
        uv = torch.cross(u, v, dim=-1)
        cols.append(v + 2.0 * w * uv + 2.0 * torch.cross(u, uv, dim=-1))
    return torch.stack(cols, dim=-1)


def _ref_sh(degree: int, sh: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Textbook real SH (Sloan's table) in 3DGS's sign convention; sh [..., K, 3], dirs [..., 3]."""
    d = dirs / dirs.norm(dim=-1, keepdim=True)
    x, y, z = d.unbind(-1)
    basis = [torch.full_like(x, 0.5 / math.sqrt(math.pi))]
    if degree >= 1:
        c1 = math.sqrt(3.0 / (4.0 * math.pi))
        basis += [-c1 * y, c1 * z, -c1 * x]
    if degree >= 2:
        basis += [
            0.5 * math.sqrt(15.0 / math.pi) * x * y,
            -0.5 * math.sqrt(15.0 / math.pi) * y * z,
            0.25 * math.sqrt(5.0 / math.pi) * (2.0 * z * z - x * x - y * y),
            -0.5 * math.sqrt(15.0 / math.pi) * x * z,
            0.25 * math.sqrt(15.0 / math.pi) * (x * x - y * y),
        ]
    if degree >= 3:
        basis += [
            -0.25 * math.sqrt(35.0 / (2.0 * math.pi)) * y * (3.0 * x * x - y * y),
            0.5 * math.sqrt(105.0 / math.pi) * x * y * z,
            -0.25 * math.sqrt(21.0 / (2.0 * math.pi)) * y * (4.0 * z * z - x * x - y * y),
            0.25 * math.sqrt(7.0 / math.pi) * z * (2.0 * z * z - 3.0 * x * x - 3.0 * y * y),
            -0.25 * math.sqrt(21.0 / (2.0 * math.pi)) * x * (4.0 * z * z - x * x - y * y),
            0.25 * math.sqrt(105.0 / math.pi) * z * (x * x - y * y),
            -0.25 * math.sqrt(35.0 / (2.0 * math.pi)) * x * (x * x - 3.0 * y * y),
        ]
    b = torch.stack(basis, dim=-1)
    return (b[..., :, None] * sh[..., : b.shape[-1], :]).sum(dim=-2)


def reference_render(
    means,
    quats,
    scales,
    opacities,
    colors,
    viewmats,
    Ks,
    width,
    height,
    *,
    near_plane=0.01,
    far_plane=1e10,
    eps2d=0.3,
    sh_degree=None,
    backgrounds=None,
    active=None,
):
    """Dense per-pixel gsplat-classic rendering; every input is used in float64."""
    means, quats, scales, opacities = (t.double() for t in (means, quats, scales, opacities))
    colors, viewmats, Ks = colors.double(), viewmats.double(), Ks.double()
    n_cams, n = viewmats.shape[0], means.shape[0]
    rot = _ref_rotmat(quats)
    cov3 = rot @ torch.diag_embed(scales**2) @ rot.transpose(-1, -2)
    if sh_degree is not None:
        campos = torch.linalg.inv(viewmats)[:, :3, 3]
        colors = torch.clamp_min(_ref_sh(sh_degree, colors, means[None] - campos[:, None]) + 0.5, 0.0)
    elif colors.dim() == 2:
        colors = colors.expand(n_cams, -1, -1)
    if backgrounds is None:
        backgrounds = torch.zeros(n_cams, colors.shape[-1], dtype=torch.float64)
    backgrounds = backgrounds.double().expand(n_cams, -1)
    if active is None:
        active = torch.ones(n, dtype=torch.bool)
    ys, xs = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    pix = torch.stack([xs, ys], dim=-1).reshape(-1, 2).double()
    images, alphas = [], []
    for c in range(n_cams):
        R, t = viewmats[c, :3, :3], viewmats[c, :3, 3]
        fx, fy, cx, cy = Ks[c, 0, 0], Ks[c, 1, 1], Ks[c, 0, 2], Ks[c, 1, 2]
        mc = means @ R.T + t
        z = mc[:, 2]
        in_depth = (z > near_plane) & (z < far_plane)
        z_safe = torch.where(in_depth, z, torch.ones_like(z))
        lim_x, lim_y = 0.3 * 0.5 * width / fx, 0.3 * 0.5 * height / fy
        tx = z_safe * torch.clamp(mc[:, 0] / z_safe, min=-(cx / fx + lim_x), max=(width - cx) / fx + lim_x)
        ty = z_safe * torch.clamp(mc[:, 1] / z_safe, min=-(cy / fy + lim_y), max=(height - cy) / fy + lim_y)
        zero = torch.zeros_like(z)
        J = torch.stack([fx / z_safe, zero, -fx * tx / z_safe**2, zero, fy / z_safe, -fy * ty / z_safe**2], dim=-1).reshape(n, 2, 3)
        cov2 = J @ R @ cov3 @ R.T @ J.transpose(-1, -2) + eps2d * torch.eye(2, dtype=torch.float64)
        det = torch.linalg.det(cov2)
        valid = in_depth & (det > 0) & (opacities >= 1.0 / 255.0) & active
        conic = torch.linalg.inv(torch.where(valid[:, None, None], cov2, torch.eye(2, dtype=torch.float64)))
        mean2d = torch.stack([fx * mc[:, 0] / z_safe + cx, fy * mc[:, 1] / z_safe + cy], dim=-1)
        d = pix[:, None, :] - mean2d[None]  # [P, N, 2]
        sigma = 0.5 * torch.einsum("pni,nij,pnj->pn", d, conic, d)
        alpha = torch.clamp(opacities[None] * torch.exp(-sigma), max=0.999)
        keep = valid[None] & (sigma >= 0) & (alpha >= 1.0 / 255.0)
        alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
        order = torch.sort(torch.where(valid, z, torch.full_like(z, math.inf)), stable=True).indices
        alpha = alpha[:, order]
        one_minus = 1.0 - alpha
        t_after = torch.cumprod(one_minus, dim=1)
        contributes = t_after > 1e-4  # monotone, so this is the prefix before termination
        t_before = torch.cat([torch.ones_like(t_after[:, :1]), t_after[:, :-1]], dim=1)
        weights = torch.where(contributes, alpha * t_before, torch.zeros_like(alpha))
        t_final = torch.where(contributes, one_minus, torch.ones_like(one_minus)).prod(dim=1)
        img = weights @ colors[c][order] + t_final[:, None] * backgrounds[c]
        images.append(img.reshape(height, width, -1))
        alphas.append((1.0 - t_final).reshape(height, width, 1))
    return torch.stack(images), torch.stack(alphas)


# --------------------------------------------------------------------------- scenes


def look_at(eye, target, up=(0.0, -1.0, 0.0)) -> torch.Tensor:
    """World-to-camera 4x4 (OpenCV: x right, y down, z forward) for a camera at eye facing target."""
    eye, target, up = (torch.tensor(v, dtype=torch.float64) for v in (eye, target, up))
    fwd = torch.nn.functional.normalize(target - eye, dim=0)
    right = torch.nn.functional.normalize(torch.linalg.cross(fwd, up), dim=0)
    down = torch.linalg.cross(fwd, right)
    R = torch.stack([right, down, fwd])
    vm = torch.eye(4, dtype=torch.float64)
    vm[:3, :3] = R
    vm[:3, 3] = -R @ eye
    return vm.float()


def intrinsics(width, height, focal) -> torch.Tensor:
    return torch.tensor([[focal, 0.0, width / 2 + 0.3], [0.0, focal, height / 2 - 0.2], [0.0, 0.0, 1.0]])


def random_scene(n, *, seed, n_cams=2, width=45, height=37, sh_degree=None, spread=1.0):
    g = torch.Generator().manual_seed(seed)
    scene = {
        "means": torch.randn(n, 3, generator=g) * spread,
        "quats": torch.randn(n, 4, generator=g),
        "scales": torch.exp(torch.randn(n, 3, generator=g) * 0.6 - 2.2),
        "opacities": torch.rand(n, generator=g) * 0.98 + 0.01,
        "colors": torch.randn(n, num_sh_bases(sh_degree), 3, generator=g) * 0.4 if sh_degree is not None else torch.rand(n, 3, generator=g),
    }
    eyes = [(0.3, -0.4, -5.0), (4.0, 1.0, -3.0), (-3.0, -2.0, 3.5)][:n_cams]
    scene["viewmats"] = torch.stack([look_at(e, (0.0, 0.0, 0.0)) for e in eyes])
    scene["Ks"] = torch.stack([intrinsics(width, height, 0.9 * width)] * n_cams)
    scene["backgrounds"] = torch.rand(n_cams, 3, generator=g)
    scene["width"], scene["height"], scene["sh_degree"] = width, height, sh_degree
    return scene


def run_both(scene, **kwargs):
    """Renders with both implementations under the same random loss; returns outputs and gradients."""
    inputs = {k: (v.clone().requires_grad_(True) if k in PARAMS else v) for k, v in scene.items()}
    kw = {k: inputs[k] for k in ("width", "height", "sh_degree", "backgrounds")} | kwargs
    args = [inputs[k] for k in ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks")]
    colors, alphas, meta = rasterize(*args, **kw)
    g = torch.Generator().manual_seed(7)
    w_col, w_alpha = torch.randn(colors.shape, generator=g), torch.randn(alphas.shape, generator=g)
    ((colors * w_col).sum() + (alphas * w_alpha).sum()).backward()
    grads = {k: inputs[k].grad for k in PARAMS}
    ref_inputs = {k: (v.clone().requires_grad_(True) if k in PARAMS else v) for k, v in scene.items()}
    kw_ref = {k: ref_inputs[k] for k in ("width", "height", "sh_degree", "backgrounds")} | kwargs
    kw_ref.pop("tile_size", None)
    ref_colors, ref_alphas = reference_render(
        *[ref_inputs[k] for k in ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks")], **kw_ref
    )
    ((ref_colors * w_col.double()).sum() + (ref_alphas * w_alpha.double()).sum()).backward()
    ref_grads = {k: ref_inputs[k].grad for k in PARAMS}
    return (colors, alphas, meta, grads), (ref_colors, ref_alphas, ref_grads)


def assert_matches(scene, **kwargs):
    (colors, alphas, meta, grads), (ref_colors, ref_alphas, ref_grads) = run_both(scene, **kwargs)
    for name, out in (("colors", colors), ("alphas", alphas)):
        assert torch.isfinite(out).all(), name
    assert colors.dtype == torch.float32
    assert (colors.double() - ref_colors).abs().max() <= 1e-5
    assert (alphas.double() - ref_alphas).abs().max() <= 1e-5
    for name in PARAMS:
        got, ref = grads[name], ref_grads[name]
        if ref is None:
            ref = torch.zeros_like(got, dtype=torch.float64)
        assert got is not None and torch.isfinite(got).all(), name
        err = (got.double() - ref).abs()
        ok = (err <= 1e-6) | (err <= 1e-3 * ref.abs())
        assert ok.all(), f"{name}: worst abs err {err.max():.3g} at ref {ref.flatten()[err.argmax()]:.3g}"
    return colors, alphas, meta, grads


# --------------------------------------------------------------------------- tests


@pytest.mark.parametrize("sh_degree", [None, 3])
def test_random_scene_matches_reference(sh_degree):
    scene = random_scene(150, seed=1 if sh_degree is None else 2, sh_degree=sh_degree)
    _, alphas, meta, _ = assert_matches(scene)
    assert alphas.max() > 0.9  # the scene is not trivially empty
    assert "visibility_counts" not in meta  # training does not read them: counted only on request
    args = [scene[k] for k in ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks")]
    counted_colors, _, counted = rasterize(
        *args, scene["width"], scene["height"], sh_degree=sh_degree, backgrounds=scene["backgrounds"], visibility_counts=True
    )
    assert counted["visibility_counts"].shape == (2, 150) and counted["visibility_counts"].sum() > 0
    assert torch.equal(
        counted_colors, rasterize(*args, scene["width"], scene["height"], sh_degree=sh_degree, backgrounds=scene["backgrounds"])[0]
    )


def test_batched_views_with_empty_tiles_match_reference():
    # The production shape in small: several views in one call, SH colours, a background per view, an
    # object on a few tiles of each image (empty tiles take the background path, and keep no float64 state: the
    # background's gradient must still see T = 1 there).
    scene = random_scene(120, seed=21, n_cams=3, width=96, height=64, sh_degree=2, spread=0.25)
    _, alphas, _, _ = assert_matches(scene, tile_size=16)
    tiles = alphas[..., 0].unfold(1, 16, 16).unfold(2, 16, 16).amax(dim=(-1, -2))
    assert (tiles == 0).any(dim=(1, 2)).all() and (tiles > 0.5).any(dim=(1, 2)).all()


def test_dense_scene_terminates_early_like_reference():
    scene = random_scene(300, seed=3, n_cams=1, width=33, height=29, spread=0.8)
    scene["opacities"] = torch.full((300,), 0.97)
    scene["scales"] = scene["scales"] * 3.0
    _, alphas, _, _ = assert_matches(scene)
    # Most pixels are covered many times over, yet T never falls to the 1e-4 floor: compositing stopped.
    assert (alphas > 0.996).float().mean() > 0.5
    assert (1.0 - alphas.double()).min() > 0.99e-4


def test_lower_sh_degree_reads_leading_coefficients():
    scene = random_scene(60, seed=4, n_cams=1, sh_degree=3)
    scene["sh_degree"] = 1
    assert_matches(scene)


def test_behind_camera_and_near_plane():
    # Camera at the origin looking down +z; Gaussians behind it, straddling and just past the near plane.
    scene = random_scene(6, seed=5, n_cams=1, width=40, height=30)
    scene["viewmats"] = torch.eye(4)[None]
    scene["means"] = torch.tensor(
        [[0.1, 0.0, -1.0], [0.0, 0.1, 0.005], [0.05, -0.02, 0.02], [0.2, 0.1, 0.3], [-3.0, 0.5, 0.05], [0.0, 0.0, 2.0]]
    )
    scene["scales"] = torch.tensor([[0.5, 0.5, 0.5], [0.3, 0.3, 0.3], [0.05, 0.08, 0.1]] + [[0.1, 0.2, 0.05]] * 3)
    _, _, meta, _ = assert_matches(scene)
    assert meta["radii"][0, :2].eq(0).all() and meta["radii"][0, 2:4].gt(0).all()


def test_extreme_shapes_and_opacities():
    scene = random_scene(8, seed=6, n_cams=2, width=31, height=23)
    scene["means"] = torch.tensor(
        [
            [0.0, 0.0, 0.0],
            [0.3, -0.2, 0.1],
            [-0.4, 0.1, 0.2],
            [0.1, 0.4, -0.3],
            [0.2, 0.2, 0.2],
            [-0.2, -0.3, 0.0],
            [0.5, 0.0, -0.1],
            [0.0, -0.5, 0.3],
        ]
    )
    scene["scales"] = (
        torch.tensor(
            [
                [1e-4, 1.0, 1.0],  # scale ratio 1e4: a disc seen at an angle
                [2e-5, 2e-5, 2e-5],  # sub-pixel: eps2d dominates
                [8.0, 6.0, 7.0],  # covers the whole image
                [1e-4, 1e-4, 1.0],  # needle
                [0.1, 0.1, 0.1],
                [0.2, 0.05, 0.1],
                [0.3, 0.3, 0.3],
                [0.15, 0.1, 0.2],
            ]
        )
        * 0.5
    )
    scene["opacities"] = torch.tensor([1.0, 1.0, 0.3, 0.0, 1.0, 0.5, 0.0, 1.0 / 255.0 + 1e-6])
    _, _, meta, grads = assert_matches(scene)
    assert grads["opacities"][6] == 0 and meta["radii"][:, 6].eq(0).all()


def test_equal_depths_break_ties_by_index():
    scene = random_scene(12, seed=8, n_cams=1, width=24, height=20)
    scene["viewmats"] = torch.eye(4)[None]
    xy = torch.randn(12, 2, generator=torch.Generator().manual_seed(0)) * 0.15
    scene["means"] = torch.cat([xy, torch.full((12, 1), 2.0)], dim=1)
    scene["quats"] = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(12, 1)
    scene["scales"] = torch.full((12, 3), 0.15)
    scene["opacities"] = torch.full((12,), 0.8)
    assert_matches(scene)
    # Same scene, order reversed: a different image, since ties follow the index.
    flipped = dict(scene, **{k: scene[k].flip(0) for k in ("means", "colors")})
    a = rasterize(*[scene[k] for k in PARAMS[:-1]], scene["Ks"], 24, 20)[0]
    b = rasterize(*[flipped[k] for k in PARAMS[:-1]], flipped["Ks"], 24, 20)[0]
    assert (a - b).abs().max() > 1e-2


def test_depths_that_tie_only_in_float32_keep_their_float64_order():
    # Depths 3 + 2^-23 (Gaussian 0) and 3 (Gaussian 1) round to the same float32: still 1 goes first.
    scene = random_scene(2, seed=18, n_cams=1, width=16, height=16)
    scene["viewmats"] = torch.eye(4)[None]
    scene["viewmats"][0, 2, 3] = 2.0
    scene["means"] = torch.tensor([[0.0, 0.0, 1.0 + 2.0**-23], [0.01, 0.0, 1.0]])
    scene["scales"] = torch.full((2, 3), 0.2)
    scene["opacities"] = torch.tensor([0.9, 0.9])
    scene["colors"] = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    colors, _, _, _ = assert_matches(scene)
    assert colors[0, 8, 8, 2] > colors[0, 8, 8, 0]  # the blue Gaussian is in front


def test_crowded_tiles_sort_like_the_reference():
    # Hundreds of splats per tile (the radix-sorted path), a third at one depth, a third at depths that tie only
    # in float32, and the rest spread: each tile's order must still be depth, then float64 depth, then index.
    n = 240
    g = torch.Generator().manual_seed(31)
    scene = random_scene(n, seed=31, n_cams=1, width=40, height=36)
    scene["viewmats"] = torch.eye(4)[None]
    depth = torch.where(torch.arange(n) % 3 == 0, torch.tensor(2.0), 2.0 + torch.rand(n, generator=g) * 0.5)
    depth = torch.where(torch.arange(n) % 3 == 1, 2.5 + (torch.arange(n) % 5) * 2.0**-22, depth)
    xy = torch.randn(n, 2, generator=g) * 0.12 * depth[:, None]
    scene["means"] = torch.cat([xy, depth[:, None]], dim=1)
    scene["scales"] = torch.full((n, 3), 0.06)
    scene["opacities"] = torch.rand(n, generator=g) * 0.2 + 0.05
    _, _, meta, _ = assert_matches(scene)
    assert meta["n_isects"] > 4 * 48  # more keys per tile than the insertion-sort path takes


def test_everything_off_screen():
    scene = random_scene(20, seed=9, n_cams=2, width=17, height=16)
    scene["means"] = scene["means"] * 0.1 + torch.tensor([40.0, 0.0, 0.0])
    colors, alphas, meta, grads = assert_matches(scene)
    assert meta["radii"].eq(0).all() and meta["n_isects"] == 0
    assert torch.equal(colors, scene["backgrounds"][:, None, None, :].expand_as(colors))
    assert alphas.eq(0).all() and grads["means"].eq(0).all()


def test_no_gaussians_at_all():
    scene = random_scene(0, seed=19, n_cams=2, width=9, height=7)
    args = [scene[k] for k in PARAMS[:-1]] + [scene["Ks"]]
    colors, alphas, meta = rasterize(*args, 9, 7, backgrounds=scene["backgrounds"], visibility_counts=True)
    assert torch.equal(colors, scene["backgrounds"][:, None, None, :].expand_as(colors)) and alphas.eq(0).all()
    assert meta["radii"].shape == (2, 0, 2) and meta["visibility_counts"].shape == (2, 0)


@pytest.mark.parametrize(("width", "height"), [(1, 1), (17, 33), (50, 3)])
def test_odd_image_sizes(width, height):
    scene = random_scene(40, seed=10 + width, n_cams=2, width=width, height=height)
    scene["scales"] = scene["scales"] * (4.0 if width == 1 else 1.0)
    assert_matches(scene)


@njit(fastmath={"contract"}, error_model="numpy")
def _listing(slot_f, slot_i, x0, y0, live, buf_p, buf_sigma):
    return kernels._ellipse_pixels(slot_f, slot_i, 0, x0, y0, live, buf_p, buf_sigma)


@njit(fastmath={"contract"}, error_model="numpy")
def _scan(slot_f, slot_i, x0, y0, live, buf_p, buf_sigma):
    """Pixel by pixel: every rect pixel whose column bit is live and whose sigma is within the slot's limit."""
    mx, my, a, b, cc, limit = slot_f[0, 0], slot_f[0, 1], slot_f[0, 2], slot_f[0, 3], slot_f[0, 4], slot_f[0, 6]
    m = 0
    for py in range(slot_i[0, 2], slot_i[0, 3] + 1):
        dy = py + 0.5 - my
        half_c_dy2 = 0.5 * cc * dy * dy
        for px in range(slot_i[0, 0], slot_i[0, 1] + 1):
            dx = px + 0.5 - mx
            sigma = 0.5 * a * dx * dx + half_c_dy2 + b * dx * dy
            if (live[py - y0] >> (px - x0)) & 1 and sigma <= limit:
                buf_p[m] = ((py - y0) << 6) + px - x0
                buf_sigma[m] = sigma
                m += 1
    return m


def assert_listing_matches_scan(tile_size: int) -> None:
    """300 random slots of one tile: the listing's pixels and sigmas equal the scan's, in the same order."""
    rng = np.random.default_rng(tile_size)
    x0, y0 = 2 * tile_size, tile_size
    room = tile_size * tile_size + kernels.LIST_LANES
    for trial in range(300):
        u_lo, u_hi = np.sort(rng.integers(x0, x0 + tile_size, 2))
        if trial % 3 == 0:
            u_hi = x0 + tile_size - 1
        v_lo, v_hi = np.sort(rng.integers(y0, y0 + tile_size, 2))
        l = rng.normal(size=(2, 2)) * rng.uniform(0.05, 0.6)
        conic = np.linalg.inv(l @ l.T + 0.1 * np.eye(2))
        centre = rng.uniform([u_lo, v_lo], [u_hi + 1, v_hi + 1])
        slot_f = np.array([[*centre, conic[0, 0], conic[0, 1], conic[1, 1], 0.9, rng.uniform(0.5, 5.0)]])
        slot_i = np.array([[u_lo, u_hi, v_lo, v_hi]], np.int32)
        full = -1 if tile_size == 64 else (1 << tile_size) - 1
        live = (rng.integers(-(2**63), 2**63 - 1, tile_size, dtype=np.int64) | (0 if trial % 2 else -1)) & full
        got_p, got_sigma = np.zeros(room, np.int64), np.zeros(room)
        want_p, want_sigma = np.zeros(room, np.int64), np.zeros(room)
        m = _listing(slot_f, slot_i, x0, y0, live, got_p, got_sigma)
        assert m == _scan(slot_f, slot_i, x0, y0, live, want_p, want_sigma)
        np.testing.assert_array_equal(got_p[:m], want_p[:m])
        np.testing.assert_array_equal(got_sigma[:m], want_sigma[:m])


@pytest.mark.parametrize("tile_size", [12, 32, 64])
def test_the_listing_keeps_what_a_pixel_by_pixel_scan_keeps(tile_size):
    # The listing packs eight pixels at a time: rects narrower and wider than eight, ending on the tile's last
    # column (bit 63 of a 64-px tile), and live masks with holes must list the same pixels, in the same order.
    assert_listing_matches_scan(tile_size)


_HASWELL = "+64bit,+avx,+avx2,+bmi,+bmi2,+cmov,+cx16,+f16c,+fma,+fxsr,+lzcnt,+movbe,+popcnt,+sse,+sse2,+sse3,+sse4.1,+sse4.2,+ssse3"


@pytest.mark.parametrize(
    ("cpu", "features", "packing"),
    [
        # Without AVX2 LLVM expands the vector compress into scalar moves: no wide register at all.
        ("x86-64", "", None),
        # With AVX2 and no AVX-512 each half of four lanes is packed by a table-driven permute (vpermd or vpermps).
        ("haswell", _HASWELL, "vperm"),
    ],
    ids=["sse2", "avx2"],
)
def test_the_listing_lists_the_same_on_a_cpu_without_avx512(tmp_path, cpu, features, packing):
    # Compiled for that CPU in a fresh process and cache, the listing must keep the same pixels, in the same order,
    # with no 512-bit register in its code.
    if packing and not numba_host_has("avx2"):
        pytest.skip("this CPU cannot run AVX2 code")
    script = (
        "from tests.reconstruction.test_render import _listing, assert_listing_matches_scan\n"
        "for tile_size in (12, 32, 64):\n"
        "    assert_listing_matches_scan(tile_size)\n"
        "code = '\\n'.join(_listing.inspect_asm().values())\n"
        "assert 'zmm' not in code, 'compiled with 512-bit registers'\n"
        + (
            f"assert {packing!r} in code, 'not packed by {packing}'\n"
            if packing
            else "assert 'ymm' not in code, 'compiled with wide vectors'\n"
        )
    )
    env = {
        **os.environ,
        "NUMBA_CPU_NAME": cpu,
        "NUMBA_CPU_FEATURES": features,
        "NUMBA_CACHE_DIR": str(tmp_path),
        "CADSPLAT_KERNEL_CACHE": str(tmp_path),
    }
    root = Path(__file__).resolve().parents[2]
    run = subprocess.run([sys.executable, "-c", script], cwd=root, env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]


def numba_host_has(feature: str) -> bool:
    from llvmlite import binding

    return bool(binding.get_host_cpu_features().get(feature))


@pytest.mark.parametrize("tile_size", [8, 12, 16, 64])
def test_tile_size_does_not_change_the_image(tile_size):
    # 64: a tile row's live-pixel mask uses all 64 bits of its int64.
    scene = random_scene(80, seed=11, n_cams=1, width=40 if tile_size == 8 else 70, height=24)
    assert_matches(scene, tile_size=tile_size)


def test_per_camera_colors_and_plain_background_vector():
    scene = random_scene(50, seed=12, n_cams=3, width=20, height=18)
    scene["colors"] = torch.rand(3, 50, 4, generator=torch.Generator().manual_seed(1))
    scene["backgrounds"] = torch.rand(3, 4, generator=torch.Generator().manual_seed(2))
    colors, _, _, _ = assert_matches(scene)
    assert colors.shape == (3, 18, 20, 4)


def test_active_subset_equals_rendering_the_subset():
    scene = random_scene(120, seed=13, n_cams=2, width=30, height=26, sh_degree=2)
    active = torch.rand(120, generator=torch.Generator().manual_seed(3)) < 0.5
    _, _, _, grads = assert_matches(scene, active=active)
    for name in ("means", "quats", "scales", "opacities", "colors"):
        assert grads[name][~active].eq(0).all(), name
    sub = {k: (scene[k][active] if k in PARAMS[:5] else scene[k]) for k in scene}
    kw = {k: sub[k] for k in ("width", "height", "sh_degree", "backgrounds")}
    full = rasterize(*[scene[k] for k in PARAMS[:-1]], scene["Ks"], active=active, **kw)
    part = rasterize(*[sub[k] for k in PARAMS[:-1]], sub["Ks"], **kw)
    assert torch.equal(full[0], part[0]) and torch.equal(full[1], part[1])


def test_results_do_not_depend_on_thread_count():
    # Enough Gaussians that every pass splits across threads (per-splat passes need 4096 per thread).
    scene = random_scene(12000, seed=14, n_cams=2, width=48, height=40)
    outs = []
    before = torch.get_num_threads()
    try:
        for threads in (1, 3):
            torch.set_num_threads(threads)
            inputs = {k: scene[k].clone().requires_grad_(True) for k in PARAMS[:-1]}
            colors, _, _ = rasterize(*inputs.values(), scene["Ks"], scene["width"], scene["height"])
            colors.square().sum().backward()
            outs.append((colors, inputs["means"].grad, inputs["viewmats"].grad))
    finally:
        torch.set_num_threads(before)
    for a, b in zip(outs[0], outs[1]):
        assert torch.equal(a, b)


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs os.fork")
def test_renders_in_a_forked_child():
    # A child forked after the thread pool started inherits the pool but not its threads.
    scene = random_scene(5000, seed=20, n_cams=1, width=64, height=64)
    args = [scene[k] for k in PARAMS[:-1]] + [scene["Ks"], 64, 64]
    expected = rasterize(*args)[0]
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.close(read_end)
        ok = torch.equal(rasterize(*args)[0], expected)
        os.write(write_end, b"1" if ok else b"0")
        os._exit(0)
    os.close(write_end)
    ready, _, _ = select.select([read_end], [], [], 60.0)
    answer = os.read(read_end, 1) if ready else b""
    os.close(read_end)
    if not ready:
        os.kill(pid, signal.SIGKILL)
    os.waitpid(pid, 0)
    assert answer == b"1"


def test_projection_meta_matches_gsplat_box_rule():
    scene = random_scene(100, seed=15, n_cams=1)
    proj = project_gaussians(
        *[scene[k] for k in ("means", "quats", "scales", "opacities", "viewmats", "Ks")], scene["width"], scene["height"]
    )
    vis = proj.radii[0, :, 0] > 0
    assert vis.any()
    cov_xx = proj.conics[0, :, 2] / (proj.conics[0, :, 0] * proj.conics[0, :, 2] - proj.conics[0, :, 1] ** 2)
    extent = torch.sqrt(2.0 * torch.log(255.0 * scene["opacities"].double()))
    assert torch.equal(proj.radii[0, vis, 0], torch.ceil(extent[vis] * cov_xx[vis].sqrt()).int())


@pytest.mark.parametrize("tile_size", [8, 12])
def test_projection_footprints_count_each_pairs_tiles(tile_size):
    scene = random_scene(120, seed=16, n_cams=3)
    args = [scene[k] for k in ("means", "quats", "scales", "opacities", "viewmats", "Ks")]
    w, h = scene["width"], scene["height"]
    plain = project_gaussians(*args, w, h)
    proj = project_gaussians(*args, w, h, tile_size=tile_size)
    assert plain.footprints is None
    for a, b in zip(plain[:4], proj[:4]):
        assert torch.equal(a, b)  # the footprints change nothing the projection returned before
    fp = proj.footprints
    n, tiles_x, tiles_y = 120, -(-w // tile_size), -(-h // tile_size)
    visible = (proj.radii[..., 0] > 0).reshape(-1).numpy()
    assert not fp.tile_counts[~visible].any()
    expected = np.zeros(3 * tiles_x * tiles_y, np.int64)
    for cg in np.flatnonzero(fp.tile_counts):
        u_lo, u_hi, v_lo, v_hi = fp.rects[cg]
        assert 0 <= u_lo <= u_hi < w and 0 <= v_lo <= v_hi < h
        tx = np.arange(u_lo // tile_size, u_hi // tile_size + 1)
        ty = np.arange(v_lo // tile_size, v_hi // tile_size + 1)
        assert fp.tile_counts[cg] == len(tx) * len(ty)
        np.add.at(expected, (cg // n) * tiles_x * tiles_y + (ty[:, None] * tiles_x + tx[None, :]).reshape(-1), 1)
    assert np.array_equal(fp.hist.sum(0), expected)  # the chunks' histograms together count every slot once
    with pytest.raises(ValueError, match="tile_size"):
        project_gaussians(*args, w, h, tile_size=-tile_size)


@pytest.mark.parametrize("per_camera", [False, True])  # numba kernels / plain-torch path
def test_eval_sh_matches_textbook_basis(per_camera):
    g = torch.Generator().manual_seed(0)
    sh = torch.randn(*((2,) if per_camera else ()), 30, 16, 3, dtype=torch.float64, generator=g)
    dirs = torch.randn(2, 30, 3, dtype=torch.float64, generator=g) * 3.0
    weights = torch.randn(2, 30, 3, dtype=torch.float64, generator=g)
    for degree in range(4):
        assert num_sh_bases(degree) == (degree + 1) ** 2
        ours = [t.clone().requires_grad_(True) for t in (sh, dirs)]
        ref = [t.clone().requires_grad_(True) for t in (sh, dirs)]
        out, ref_out = eval_sh(degree, *ours), _ref_sh(degree, *ref)
        assert torch.allclose(out, ref_out, atol=1e-12)
        (out * weights).sum().backward()
        (ref_out * weights).sum().backward()
        assert torch.allclose(ours[0].grad, ref[0].grad, atol=1e-12)
        # Degree 0 does not depend on the directions: no gradient, or a zero one.
        dirs_grads = [t.grad if t.grad is not None else torch.zeros_like(t) for t in (ours[1], ref[1])]
        assert torch.allclose(*dirs_grads, rtol=1e-10, atol=1e-10)
    # A camera centre on a Gaussian: a zero direction gives finite values and gradients.
    zero = torch.zeros(2, 30, 3, dtype=torch.float64, requires_grad=True)
    eval_sh(3, sh, zero).sum().backward()
    assert torch.isfinite(zero.grad).all()
    with pytest.raises(ValueError):
        num_sh_bases(4)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_colors_match_the_torch_formula_and_its_gradients(degree):
    # The rasterizer's colour, max(SH(mean - camera centre) + 0.5, 0), in one kernel pass each way, against the same
    # formula in plain torch through autograd (per-camera coefficients take that path), with some colours clamped
    # at 0 and a camera centre on a Gaussian (a zero direction, which F.normalize floors).
    g = torch.Generator().manual_seed(3 + degree)
    sh = torch.randn(150, 16, 3, dtype=torch.float64, generator=g) * 0.6
    means = torch.randn(150, 3, dtype=torch.float64, generator=g)
    campos = torch.randn(4, 3, dtype=torch.float64, generator=g) * 3.0
    campos[2] = means[7]
    weights = torch.randn(4, 150, 3, dtype=torch.float64, generator=g)
    ours = [t.clone().requires_grad_(True) for t in (sh, means, campos)]
    ref = [t.clone().requires_grad_(True) for t in (sh, means, campos)]
    out = sh_colors(degree, *ours)
    ref_out = sh_colors(degree, ref[0].expand(4, -1, -1, -1), *ref[1:])
    assert out.shape == (4, 150, 3) and (ref_out == 0).any() and (ref_out > 0).any()
    assert torch.allclose(out, ref_out, rtol=0, atol=1e-13)
    (out * weights).sum().backward()
    (ref_out * weights).sum().backward()
    for name, a, b in zip(("sh", "means", "campos"), ours, ref):
        # Degree 0 does not depend on the directions: torch has no gradient there, the kernel a zero one.
        expected = b.grad if b.grad is not None else torch.zeros_like(b)
        assert torch.allclose(a.grad, expected, rtol=1e-12, atol=1e-12), name


def test_rejects_bad_shapes():
    scene = random_scene(10, seed=16, n_cams=1)
    args = [scene[k] for k in PARAMS[:-1]] + [scene["Ks"]]
    args[1] = args[1][:, :3]
    with pytest.raises(ValueError, match="quats"):
        rasterize(*args, 10, 10)
    args[1] = scene["quats"]
    with pytest.raises(ValueError, match="tile_size"):
        rasterize(*args, 10, 10, tile_size=65)


@pytest.mark.skipif(
    not (torch.cuda.is_available() and __import__("importlib").util.find_spec("gsplat")),
    reason="needs a CUDA GPU and gsplat",
)
def test_cuda_backend_agrees_with_cpu():
    scene = random_scene(300, seed=17, n_cams=2, width=64, height=48, sh_degree=3)
    outs = {}
    for device in ("cpu", "cuda"):
        inputs = {k: scene[k].to(device).requires_grad_(True) for k in PARAMS}
        colors, alphas, meta = rasterize(
            *[inputs[k] for k in PARAMS[:-1]],
            scene["Ks"].to(device),
            64,
            48,
            sh_degree=3,
            backgrounds=inputs["backgrounds"],
            visibility_counts=True,
        )
        (colors.square().sum() + alphas.sum()).backward()
        outs[device] = (colors, alphas, meta["visibility_counts"], {k: inputs[k].grad for k in PARAMS})
    cpu, gpu = outs["cpu"], outs["cuda"]
    assert (cpu[0] - gpu[0].cpu()).abs().max() < 1e-4
    assert (cpu[1] - gpu[1].cpu()).abs().max() < 1e-4
    assert (cpu[2] - gpu[2].cpu()).abs().sum() <= 0.01 * cpu[2].sum()
    for k in PARAMS:
        assert torch.allclose(cpu[3][k], gpu[3][k].cpu(), rtol=1e-2, atol=1e-4), k
    # Alphas alone: gsplat has no zero-channel kernel, so the backend draws one zero channel and drops it.
    alphas_only = {}
    for device in ("cpu", "cuda"):
        args = [scene[k].to(device) for k in PARAMS[:4]]
        colors, alphas, _ = rasterize(
            *args, torch.zeros(300, 0, device=device), scene["viewmats"].to(device), scene["Ks"].to(device), 64, 48
        )
        assert colors.shape == (2, 48, 64, 0)
        alphas_only[device] = alphas.cpu()
    assert (alphas_only["cpu"] - alphas_only["cuda"]).abs().max() < 1e-4


def test_interleaved_renders_keep_their_own_scratch_buffers():
    # The pairs a forward keeps for its backward come from a shared pool: two graphs alive at once and
    # a no-grad render between them must not share a buffer.
    scene = random_scene(400, seed=23, n_cams=2, width=64, height=48, sh_degree=1)

    def render(grad: bool):
        inputs = {k: scene[k].clone().requires_grad_(grad) for k in PARAMS[:-1]}
        colors, alphas, _ = rasterize(*inputs.values(), scene["Ks"], scene["width"], scene["height"], sh_degree=1)
        return inputs, (colors.square().sum() + alphas.sum())

    alone_inputs, alone_loss = render(True)
    alone_loss.backward()
    first_inputs, first_loss = render(True)
    second_inputs, second_loss = render(True)
    with torch.no_grad():
        render(False)
        render(True)  # inputs that require grad, but no graph: its pairs go straight back to the pool
    second_loss.backward()
    first_loss.backward()
    for inputs in (first_inputs, second_inputs):
        for name in ("means", "scales", "opacities", "colors"):
            assert torch.equal(inputs[name].grad, alone_inputs[name].grad), name
    # A retained graph's second backward composites again for the pairs the first one gave back.
    twice_inputs, loss = render(True)
    loss.backward(retain_graph=True)
    loss.backward()
    for name in ("means", "scales", "opacities", "colors"):
        assert torch.equal(twice_inputs[name].grad, 2 * alone_inputs[name].grad), name


def test_a_loss_on_one_image_differentiates_like_zero_weight_on_the_other():
    # Stage I's loss reads only the alphas and Stage II's photometric term could read only the colours: the image the
    # loss ignores reaches the backward as nothing at all, which must equal an explicit zero weight on it.
    scene = random_scene(200, seed=29, n_cams=2, width=48, height=40)

    def grads(loss_of):
        inputs = {k: scene[k].clone().requires_grad_(True) for k in PARAMS}
        colors, alphas, _ = rasterize(
            *[inputs[k] for k in PARAMS[:-1]], scene["Ks"], scene["width"], scene["height"], backgrounds=inputs["backgrounds"]
        )
        loss_of(colors, alphas).backward()
        return {k: inputs[k].grad for k in PARAMS}

    for alone, weighted in (
        (lambda c, a: a.square().sum(), lambda c, a: a.square().sum() + 0.0 * c.sum()),
        (lambda c, a: c.square().sum(), lambda c, a: c.square().sum() + 0.0 * a.sum()),
    ):
        got, want = grads(alone), grads(weighted)
        for name in PARAMS:
            if got[name] is None:
                assert name == "backgrounds" and not want[name].any()
            else:
                assert torch.equal(got[name], want[name]), name


def test_alphas_alone_render_and_differentiate_like_a_zero_colour():
    # Training's silhouette renders carry no colour channel ([N, 0]): the compositing then tracks the transmittance
    # alone, and the alphas and every gradient must be those of a zero colour, to the bit.
    scene = random_scene(250, seed=31, n_cams=2, width=48, height=40)
    weights = torch.randn(2, 40, 48, 1, generator=torch.Generator().manual_seed(5))

    def render(depth: int):
        inputs = {k: scene[k].clone().requires_grad_(True) for k in ("means", "quats", "scales", "opacities", "viewmats")}
        colors, alphas, _ = rasterize(
            inputs["means"],
            inputs["quats"],
            inputs["scales"],
            inputs["opacities"],
            torch.zeros(250, depth),
            inputs["viewmats"],
            scene["Ks"],
            scene["width"],
            scene["height"],
        )
        (alphas * weights).sum().backward()
        return colors, alphas, {k: v.grad for k, v in inputs.items()}

    colors, alphas, grads = render(0)
    _, zero_colour_alphas, zero_colour_grads = render(1)
    assert colors.shape == (2, 40, 48, 0)
    assert alphas.max() > 0.9 and torch.equal(alphas, zero_colour_alphas)
    for name, grad in grads.items():
        assert grad.abs().max() > 0 and torch.equal(grad, zero_colour_grads[name]), name


def test_gradients_without_quats_or_scales_equal_those_of_the_full_graph():
    # Stage I trains the pose and the deformed means only: the projection then skips the covariance's gradient, and
    # what it does return must not move by a bit.
    scene = random_scene(250, seed=37, n_cams=2, width=48, height=40, sh_degree=1)
    weights = torch.randn(2, 40, 48, 3, generator=torch.Generator().manual_seed(9))

    def grads(learn: tuple[str, ...]):
        inputs = {k: scene[k].clone().requires_grad_(k in learn) for k in PARAMS[:-1]}
        colors, alphas, _ = rasterize(*inputs.values(), scene["Ks"], scene["width"], scene["height"], sh_degree=1)
        ((colors * weights).sum() + alphas.sum()).backward()
        return {k: v.grad for k, v in inputs.items()}

    full = grads(PARAMS[:-1])
    partial = grads(("means", "viewmats", "opacities", "colors"))
    assert partial["quats"] is None and partial["scales"] is None
    for name in ("means", "viewmats", "opacities", "colors"):
        assert partial[name].abs().max() > 0 and torch.equal(partial[name], full[name]), name


def test_the_three_channel_backward_equals_the_backward_for_any_depth(monkeypatch):
    # Stage II's RGB renders differentiate in a kernel of their own (two passes over each slot's pixels, so that its
    # sums fit the registers): every gradient must be the general kernel's, to the bit.
    scene = random_scene(250, seed=43, n_cams=2, width=48, height=40, sh_degree=2, spread=0.6)
    weights = torch.randn(2, 40, 48, 3, generator=torch.Generator().manual_seed(11))

    def grads():
        inputs = {k: scene[k].clone().requires_grad_(True) for k in PARAMS}
        colors, alphas, _ = rasterize(
            *[inputs[k] for k in PARAMS[:-1]], scene["Ks"], scene["width"], scene["height"], sh_degree=2, backgrounds=inputs["backgrounds"]
        )
        ((colors * weights).sum() + alphas.sum()).backward()
        return {k: v.grad for k, v in inputs.items()}

    rgb = grads()
    monkeypatch.setattr(kernels, "rasterize_backward_rgb", kernels.rasterize_backward)
    general = grads()
    for name in PARAMS:
        assert rgb[name].abs().max() > 0 and torch.equal(rgb[name], general[name]), name


def test_a_pair_on_the_alpha_cut_off_is_decided_as_in_float64():
    # Why the rasterizer stays in float64 (issue 20): the 1/255 cut-off puts a pixel's alpha on or off in one step of
    # ~4e-3. Here an opacity is found, one float32 ulp at a time, at which the float64 reference and the same formula in
    # float32 decide a pair differently; the rasterizer must decide it as the reference does.
    fx, z, s = 100.0, 1.0, np.float32(0.02)
    px, py = 4.5, 0.5  # the pixel (12, 8) from the splat's centre, which projects to the corner (8, 8)
    var64 = (fx * float(s) / z) ** 2 + 0.3
    sigma64 = 0.5 * (px * px + py * py) / var64
    var32 = np.float32(fx) * s / np.float32(z)
    var32 = var32 * var32 + np.float32(0.3)
    sigma32 = np.float32(0.5) * (np.float32(px) * np.float32(px) + np.float32(py) * np.float32(py)) / var32
    threshold32 = np.float32(1.0 / 255.0)
    opacity = np.float32(1.0 / 255.0 / math.exp(-sigma64) * (1 - 1e-6))
    for _ in range(200):
        on64 = float(opacity) * math.exp(-sigma64) >= 1.0 / 255.0
        on32 = opacity * np.exp(-sigma32) >= threshold32
        if on64 != on32:
            break
        opacity = np.nextafter(opacity, np.float32(1.0))
    assert on64 != on32, "float32 decided every opacity like float64"
    scene = random_scene(1, seed=3, n_cams=1, width=16, height=16)
    scene["viewmats"] = torch.eye(4)[None]
    scene["Ks"] = torch.tensor([[[fx, 0.0, 8.0], [0.0, fx, 8.0], [0.0, 0.0, 1.0]]])
    scene["means"] = torch.tensor([[0.0, 0.0, z]])
    scene["scales"] = torch.full((1, 3), float(s))
    scene["opacities"] = torch.tensor([float(opacity)])
    scene["colors"] = torch.ones(1, 3)
    _, alphas, _, _ = assert_matches(scene)
    expected = float(opacity) * math.exp(-sigma64) if on64 else 0.0
    assert abs(float(alphas.detach()[0, 8, 12, 0]) - expected) <= 1e-6  # a float32 decision would be ~4e-3 off here
