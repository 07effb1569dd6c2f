"""Real spherical harmonics up to degree 3, in gsplat's (and 3DGS's) basis order and sign convention.

Pure PyTorch, so autograd reaches both the coefficients and the view directions (and, through them,
Gaussian means and camera poses). The rasterizer turns the result into a colour as
clamp(eval_sh(...) + 0.5, min=0), which is 3DGS's convention.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

MAX_SH_DEGREE = 3

# Basis constants, in the polynomial form gsplat's CUDA kernels use (which assumes unit directions).
_C0 = 0.2820947917738781
_C1 = 0.48860251190292
_C2_XY = 0.5462742152960395
_C2_Z = -1.092548430592079
_C2_ZZ = (0.9461746957575601, -0.3153915652525201)
_C3_Z2 = (-2.285228997322329, 0.4570457994644658)
_C3_Z = 1.445305721320277
_C3_A = -0.5900435899266435
_C3_ZZZ = (1.865881662950577, -1.119528997770346)


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
    out = [torch.full_like(dirs[..., 0], _C0)]
    if degree >= 1:
        x, y, z = dirs.unbind(-1)
        out += [-_C1 * y, _C1 * z, -_C1 * x]
    if degree >= 2:
        zz = z * z
        c1 = x * x - y * y
        s1 = 2.0 * x * y
        out += [_C2_XY * s1, _C2_Z * z * y, _C2_ZZ[0] * zz + _C2_ZZ[1], _C2_Z * z * x, _C2_XY * c1]
    if degree >= 3:
        tmp_c = _C3_Z2[0] * zz + _C3_Z2[1]
        c2 = x * c1 - y * s1
        s2 = x * s1 + y * c1
        out += [
            _C3_A * s2,
            _C3_Z * z * s1,
            tmp_c * y,
            z * (_C3_ZZZ[0] * zz + _C3_ZZZ[1]),
            tmp_c * x,
            _C3_Z * z * c1,
            _C3_A * c2,
        ]
    return torch.stack(out, dim=-1)


def eval_sh(degree: int, sh: Tensor, dirs: Tensor) -> Tensor:
    """Evaluates SH coefficients along view directions.

    Args:
        degree: SH degree to use, 0..3; only the first (degree + 1) ** 2 coefficients are read, so a
            model holding degree-3 coefficients can be evaluated at a lower degree (as in 3DGS's
            progressive SH schedule).
        sh: [..., K, 3] coefficients (K >= (degree + 1) ** 2), broadcastable against dirs.
        dirs: [..., 3] view directions, any length (normalised here; a zero vector gives the DC term
            only, without NaN).

    Returns:
        [..., 3] the SH value (no +0.5 offset, no clamping).
    """
    n_bases = num_sh_bases(degree)
    if sh.shape[-2] < n_bases:
        raise ValueError(f"degree {degree} needs {n_bases} SH coefficients per channel, got {sh.shape[-2]}")
    bases = sh_bases(degree, F.normalize(dirs, dim=-1))
    return torch.matmul(bases.unsqueeze(-2), sh[..., :n_bases, :]).squeeze(-2)
