"""Numba kernels for spherical harmonics colours, forward and VJP, and the basis constants.

Autograd through ~35 small torch ops per evaluation cost more than the whole forward+backward
rasterization at 20k Gaussians; one fused pass per Gaussian costs about a millisecond. Every float
array is float64; sh is [N, K, 3] and dirs [R, N, 3] (R = cameras or any flattened leading dims).
Kernels run over a Gaussian range (lo, hi) and loop over the R rows inside, so the SH gradient of a
Gaussian is summed over rows by one thread, in a fixed order.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

# Basis constants in the polynomial form gsplat's CUDA kernels use (which assumes unit directions).
_C0 = 0.2820947917738781
_C1 = 0.48860251190292
_C2_XY = 0.5462742152960395
_C2_Z = -1.092548430592079
_C2_ZZ = (0.9461746957575601, -0.3153915652525201)
_C3_Z2 = (-2.285228997322329, 0.4570457994644658)
_C3_Z = 1.445305721320277
_C3_A = -0.5900435899266435
_C3_ZZZ = (1.865881662950577, -1.119528997770346)
# torch.nn.functional.normalize's default floor on the norm.
NORMALIZE_EPS = 1e-12

_OPTS = {"cache": True, "error_model": "numpy", "nogil": True}


@njit(inline="always", **_OPTS)
def _unit(d0, d1, d2):
    """(x, y, z, |d|) with (x, y, z) = d / max(|d|, eps), as torch.nn.functional.normalize."""
    norm = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    denom = max(norm, NORMALIZE_EPS)
    return d0 / denom, d1 / denom, d2 / denom, norm


@njit(inline="always", **_OPTS)
def _bases(n_bases, x, y, z, b, bx, by, bz) -> None:
    """Basis values b[k] and their partial derivatives bx, by, bz w.r.t. the unit direction."""
    b[0] = _C0
    bx[0] = by[0] = bz[0] = 0.0
    if n_bases == 1:
        return
    b[1], bx[1], by[1], bz[1] = -_C1 * y, 0.0, -_C1, 0.0
    b[2], bx[2], by[2], bz[2] = _C1 * z, 0.0, 0.0, _C1
    b[3], bx[3], by[3], bz[3] = -_C1 * x, -_C1, 0.0, 0.0
    if n_bases == 4:
        return
    zz = z * z
    c1 = x * x - y * y
    s1 = 2.0 * x * y
    b[4], bx[4], by[4], bz[4] = _C2_XY * s1, 2.0 * _C2_XY * y, 2.0 * _C2_XY * x, 0.0
    b[5], bx[5], by[5], bz[5] = _C2_Z * z * y, 0.0, _C2_Z * z, _C2_Z * y
    b[6], bx[6], by[6], bz[6] = _C2_ZZ[0] * zz + _C2_ZZ[1], 0.0, 0.0, 2.0 * _C2_ZZ[0] * z
    b[7], bx[7], by[7], bz[7] = _C2_Z * z * x, _C2_Z * z, 0.0, _C2_Z * x
    b[8], bx[8], by[8], bz[8] = _C2_XY * c1, 2.0 * _C2_XY * x, -2.0 * _C2_XY * y, 0.0
    if n_bases == 9:
        return
    tmp_c = _C3_Z2[0] * zz + _C3_Z2[1]
    b[9], bx[9], by[9], bz[9] = _C3_A * (x * s1 + y * c1), 6.0 * _C3_A * x * y, 3.0 * _C3_A * c1, 0.0
    b[10], bx[10], by[10], bz[10] = _C3_Z * z * s1, 2.0 * _C3_Z * y * z, 2.0 * _C3_Z * x * z, _C3_Z * s1
    b[11], bx[11], by[11], bz[11] = tmp_c * y, 0.0, tmp_c, 2.0 * _C3_Z2[0] * z * y
    b[12], bx[12], by[12], bz[12] = z * (_C3_ZZZ[0] * zz + _C3_ZZZ[1]), 0.0, 0.0, 3.0 * _C3_ZZZ[0] * zz + _C3_ZZZ[1]
    b[13], bx[13], by[13], bz[13] = tmp_c * x, tmp_c, 0.0, 2.0 * _C3_Z2[0] * z * x
    b[14], bx[14], by[14], bz[14] = _C3_Z * z * c1, 2.0 * _C3_Z * z * x, -2.0 * _C3_Z * z * y, _C3_Z * c1
    b[15], bx[15], by[15], bz[15] = _C3_A * (x * c1 - y * s1), 3.0 * _C3_A * c1, -6.0 * _C3_A * x * y, 0.0


@njit(**_OPTS)
def sh_forward(lo, hi, n_bases, sh, dirs, out) -> None:
    """out[r, g] = sum_k basis_k(dirs[r, g] / |dirs[r, g]|) sh[g, k] for Gaussians lo..hi-1."""
    b = np.empty(16)
    bx = np.empty(16)
    by = np.empty(16)
    bz = np.empty(16)
    for g in range(lo, hi):
        for r in range(dirs.shape[0]):
            x, y, z, _ = _unit(dirs[r, g, 0], dirs[r, g, 1], dirs[r, g, 2])
            _bases(n_bases, x, y, z, b, bx, by, bz)
            for c in range(3):
                total = 0.0
                for k in range(n_bases):
                    total += b[k] * sh[g, k, c]
                out[r, g, c] = total


@njit(**_OPTS)
def sh_backward(lo, hi, n_bases, sh, dirs, v_out, v_sh, v_dirs) -> None:
    """VJP of `sh_forward`: accumulates v_sh [N, K, 3] (zero-initialised) and writes v_dirs [R, N, 3]."""
    b = np.empty(16)
    bx = np.empty(16)
    by = np.empty(16)
    bz = np.empty(16)
    for g in range(lo, hi):
        for r in range(dirs.shape[0]):
            x, y, z, norm = _unit(dirs[r, g, 0], dirs[r, g, 1], dirs[r, g, 2])
            _bases(n_bases, x, y, z, b, bx, by, bz)
            vx = 0.0
            vy = 0.0
            vz = 0.0
            for k in range(n_bases):
                v_basis = 0.0
                for c in range(3):
                    v_sh[g, k, c] += v_out[r, g, c] * b[k]
                    v_basis += v_out[r, g, c] * sh[g, k, c]
                vx += v_basis * bx[k]
                vy += v_basis * by[k]
                vz += v_basis * bz[k]
            # Through d / max(|d|, eps): project out the radial part, unless the clamp is active.
            if norm > NORMALIZE_EPS:
                radial = x * vx + y * vy + z * vz
                v_dirs[r, g, 0] = (vx - x * radial) / norm
                v_dirs[r, g, 1] = (vy - y * radial) / norm
                v_dirs[r, g, 2] = (vz - z * radial) / norm
            else:
                v_dirs[r, g, 0] = vx / NORMALIZE_EPS
                v_dirs[r, g, 1] = vy / NORMALIZE_EPS
                v_dirs[r, g, 2] = vz / NORMALIZE_EPS
