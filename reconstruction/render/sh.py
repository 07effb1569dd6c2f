"""Real spherical harmonics up to degree 3, in gsplat's (and 3DGS's) basis order and sign convention.

`eval_sh` is differentiable w.r.t. both the coefficients and the view directions (and, through
them, Gaussian means and camera poses). On CPU, coefficients [N, K, 3] with directions [..., N, 3]
go through fused numba kernels; anything else (CUDA tensors, per-camera coefficients) through the
same formulas in plain torch. `sh_colors` is the rasterizer's colour, max(SH + 0.5, 0) (3DGS's
convention) along mean - camera centre, in one pass each way that forms no array of directions.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor
from torch.autograd.function import once_differentiable

from reconstruction.parallel import parallel_for
from reconstruction.render import _sh_kernels as kernels

MAX_SH_DEGREE = 3
_GRAIN = 2048 // kernels.BLOCK  # blocks of Gaussians


def _check_degree(degree: int) -> None:
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"SH degree must be between 0 and {MAX_SH_DEGREE}, got {degree}")


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients per channel for `degree` (0 -> 1, 1 -> 4, 2 -> 9, 3 -> 16)."""
    _check_degree(degree)
    return (degree + 1) ** 2


def sh_bases(degree: int, dirs: Tensor) -> Tensor:
    """SH basis functions at unit directions.

    Args:
        degree: 0..3.
        dirs: [..., 3] unit vectors.

    Returns:
        [..., (degree + 1) ** 2] basis values, ordered (l, m) = (0, 0), (1, -1), (1, 0), (1, 1), ...
    """
    _check_degree(degree)
    out = [torch.full_like(dirs[..., 0], kernels._C0)]
    if degree >= 1:
        x, y, z = dirs.unbind(-1)
        out += [-kernels._C1 * y, kernels._C1 * z, -kernels._C1 * x]
    if degree >= 2:
        zz = z * z
        c1 = x * x - y * y
        s1 = 2.0 * x * y
        c2_zz, c2_z, c2_xy = kernels._C2_ZZ, kernels._C2_Z, kernels._C2_XY
        out += [c2_xy * s1, c2_z * z * y, c2_zz[0] * zz + c2_zz[1], c2_z * z * x, c2_xy * c1]
    if degree >= 3:
        tmp_c = kernels._C3_Z2[0] * zz + kernels._C3_Z2[1]
        c3_a, c3_z, c3_zzz = kernels._C3_A, kernels._C3_Z, kernels._C3_ZZZ
        out += [
            c3_a * (x * s1 + y * c1),
            c3_z * z * s1,
            tmp_c * y,
            z * (c3_zzz[0] * zz + c3_zzz[1]),
            tmp_c * x,
            c3_z * z * c1,
            c3_a * (x * c1 - y * s1),
        ]
    return torch.stack(out, dim=-1)


class _SHValues(torch.autograd.Function):
    """sh [N, K, 3] along points [P, N, 3] less origins [R, 3] (P = R, or 1 for all rows) -> [R, N, 3], all float64,
    with the numba kernels; with `colour`, max(value + 0.5, 0)."""

    @staticmethod
    def forward(ctx, n_bases, colour, sh, points, origins):
        sh_np, points_np, origins_np = (t.detach().contiguous().numpy() for t in (sh, points, origins))
        out = torch.empty((origins.shape[0], sh.shape[0], 3), dtype=torch.float64)
        parallel_for(kernels.sh_forward, _blocks(sh), n_bases, sh_np, points_np, origins_np, colour, out.numpy(), grain=_GRAIN)
        ctx.save_for_backward(sh, points, origins)
        ctx.n_bases, ctx.colour = n_bases, colour
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, v_out):
        sh, points, origins = ctx.saved_tensors
        # The kernel writes the first n_bases coefficients; only those past them need zeros. Allocated by numpy: torch's
        # zero fill of the whole array ran on its OpenMP workers, whose wake-up cost more than the fill
        # (benchmarks/results/rasterizer.md).
        v_sh = np.empty(sh.shape)
        v_sh[:, ctx.n_bases :] = 0.0
        v_points = torch.empty(points.shape, dtype=torch.float64)
        v_origins = np.empty((_blocks(sh), origins.shape[0], 3))
        parallel_for(
            kernels.sh_backward,
            _blocks(sh),
            ctx.n_bases,
            *(t.detach().contiguous().numpy() for t in (sh, points, origins)),
            ctx.colour,
            v_out.contiguous().numpy(),
            v_sh,
            v_points.numpy(),
            v_origins,
            grain=_GRAIN,
        )
        return None, None, torch.from_numpy(v_sh), v_points, torch.from_numpy(v_origins.sum(axis=0))


def _blocks(sh: Tensor) -> int:
    return -(-sh.shape[0] // kernels.BLOCK)


def sh_colors(degree: int, sh: Tensor, means: Tensor, campos: Tensor) -> Tensor:
    """3DGS's colours of Gaussians seen from camera centres: max(SH(means - campos) + 0.5, 0), as gsplat.

    Args:
        degree: 0..3 (the first (degree + 1) ** 2 coefficients are read).
        sh: [N, K, 3] coefficients, or [C, N, K, 3] per camera; means: [N, 3]; campos: [C, 3] camera centres.

    Returns:
        [C, N, 3] in the promoted dtype of the inputs. On CPU with [N, K, 3] coefficients one numba pass each way,
        with no [C, N, 3] array of directions (gradients reach sh, means and campos).
    """
    n_bases = num_sh_bases(degree)
    if sh.shape[-2] < n_bases:
        raise ValueError(f"degree {degree} needs {n_bases} SH coefficients per channel, got {sh.shape[-2]}")
    if sh.shape[-3] != means.shape[0]:
        raise ValueError(f"sh holds {sh.shape[-3]} Gaussians' coefficients and means {means.shape[0]} positions")
    if sh.is_cuda or means.is_cuda or sh.dim() != 3:
        return torch.clamp_min(eval_sh(degree, sh, means[None, :, :] - campos[:, None, :]) + 0.5, 0.0)
    dtype = torch.promote_types(torch.promote_types(sh.dtype, means.dtype), campos.dtype)
    sh, means, campos = (t.to(torch.float64) for t in (sh, means, campos))
    return _SHValues.apply(n_bases, True, sh, means[None], campos).to(dtype)


def eval_sh(degree: int, sh: Tensor, dirs: Tensor) -> Tensor:
    """Evaluates SH coefficients along view directions.

    Args:
        degree: SH degree to use, 0..3; only the first (degree + 1) ** 2 coefficients are read, so a
            model holding degree-3 coefficients can be evaluated at a lower degree (as in 3DGS's
            progressive SH schedule).
        sh: [..., K, 3] coefficients (K >= (degree + 1) ** 2), broadcastable against dirs.
        dirs: [..., 3] view directions, any length (normalised here as F.normalize does, so a zero
            vector gives finite values and gradients).

    Returns:
        [..., 3] the SH value (no +0.5 offset, no clamping), in the promoted dtype of the inputs.
    """
    n_bases = num_sh_bases(degree)
    if sh.shape[-2] < n_bases:
        raise ValueError(f"degree {degree} needs {n_bases} SH coefficients per channel, got {sh.shape[-2]}")
    n = sh.shape[0]
    if not (sh.is_cuda or dirs.is_cuda) and sh.dim() == 3 and dirs.dim() >= 2 and dirs.shape[-2] == n:
        dtype = torch.promote_types(sh.dtype, dirs.dtype)
        rows = dirs.to(torch.float64).reshape(-1, n, 3)
        origins = torch.zeros(rows.shape[0], 3, dtype=torch.float64)
        return _SHValues.apply(n_bases, False, sh.to(torch.float64), rows, origins).view(dirs.shape).to(dtype)
    bases = sh_bases(degree, F.normalize(dirs, dim=-1, eps=kernels.NORMALIZE_EPS))
    return torch.einsum("...k,...kc->...c", bases, sh[..., :n_bases, :])
