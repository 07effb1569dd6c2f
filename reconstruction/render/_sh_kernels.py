"""Numba kernels for spherical harmonics colours, forward and VJP, and the basis constants.

Autograd through ~35 small torch ops per evaluation cost more than the whole forward+backward
rasterization; one fused pass per Gaussian costs a small part of it (benchmarks/results/rasterizer.md). Every float
array is float64; sh is [N, K, 3]. The directions are points [P, N, 3] less origins [R, 3], with P = R or
P = 1 (one point per Gaussian, seen from R camera centres): the rasterizer's colours then need no [R, N, 3]
array of directions either way, and `eval_sh` passes its directions as points with zero origins.
Kernels run over blocks of `BLOCK` Gaussians (lo, hi index blocks) and loop over the R rows inside, so
a Gaussian's gradients are summed over rows by one thread, in a fixed order, and each row's sums over
Gaussians per block.
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


# Gaussians per block: a block's bases are evaluated band by band over arrays [16, BLOCK], so that each band's
# formulas, and the sums over bases, run as vector loops over the block.
BLOCK = 64


@njit(inline="always", **_OPTS)
def _directions(points, origin, m, x, y, z, norm) -> None:
    """x, y, z [m] = d / max(|d|, eps) with d = points [m, 3] - origin [3], as torch.nn.functional.normalize;
    norm [m] = |d|."""
    o0, o1, o2 = origin[0], origin[1], origin[2]
    for i in range(m):
        d0 = points[i, 0] - o0
        d1 = points[i, 1] - o1
        d2 = points[i, 2] - o2
        n = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        denom = max(n, NORMALIZE_EPS)
        x[i] = d0 / denom
        y[i] = d1 / denom
        z[i] = d2 / denom
        norm[i] = n


@njit(inline="always", **_OPTS)
def _bases(n_bases, m, x, y, z, b, bx, by, bz, grad) -> None:
    """Basis values b [k, i] at the unit directions (x, y, z) [i] of a block of m and, with `grad`, their partial
    derivatives bx, by, bz [k, i] w.r.t. the direction (the zeros too, so that every sum over k has all its terms)."""
    for i in range(m):
        b[0, i] = _C0
    if grad:
        for i in range(m):
            bx[0, i] = by[0, i] = bz[0, i] = 0.0
    if n_bases == 1:
        return
    for i in range(m):
        b[1, i] = -_C1 * y[i]
        b[2, i] = _C1 * z[i]
        b[3, i] = -_C1 * x[i]
    if grad:
        for i in range(m):
            bx[1, i], by[1, i], bz[1, i] = 0.0, -_C1, 0.0
            bx[2, i], by[2, i], bz[2, i] = 0.0, 0.0, _C1
            bx[3, i], by[3, i], bz[3, i] = -_C1, 0.0, 0.0
    if n_bases == 4:
        return
    for i in range(m):
        xi, yi, zi = x[i], y[i], z[i]
        b[4, i] = _C2_XY * (2.0 * xi * yi)
        b[5, i] = _C2_Z * zi * yi
        b[6, i] = _C2_ZZ[0] * (zi * zi) + _C2_ZZ[1]
        b[7, i] = _C2_Z * zi * xi
        b[8, i] = _C2_XY * (xi * xi - yi * yi)
    if grad:
        for i in range(m):
            xi, yi, zi = x[i], y[i], z[i]
            bx[4, i], by[4, i], bz[4, i] = 2.0 * _C2_XY * yi, 2.0 * _C2_XY * xi, 0.0
            bx[5, i], by[5, i], bz[5, i] = 0.0, _C2_Z * zi, _C2_Z * yi
            bx[6, i], by[6, i], bz[6, i] = 0.0, 0.0, 2.0 * _C2_ZZ[0] * zi
            bx[7, i], by[7, i], bz[7, i] = _C2_Z * zi, 0.0, _C2_Z * xi
            bx[8, i], by[8, i], bz[8, i] = 2.0 * _C2_XY * xi, -2.0 * _C2_XY * yi, 0.0
    if n_bases == 9:
        return
    for i in range(m):
        xi, yi, zi = x[i], y[i], z[i]
        zz = zi * zi
        c1 = xi * xi - yi * yi
        s1 = 2.0 * xi * yi
        tmp_c = _C3_Z2[0] * zz + _C3_Z2[1]
        b[9, i] = _C3_A * (xi * s1 + yi * c1)
        b[10, i] = _C3_Z * zi * s1
        b[11, i] = tmp_c * yi
        b[12, i] = zi * (_C3_ZZZ[0] * zz + _C3_ZZZ[1])
        b[13, i] = tmp_c * xi
        b[14, i] = _C3_Z * zi * c1
        b[15, i] = _C3_A * (xi * c1 - yi * s1)
        if grad:
            bx[9, i], by[9, i], bz[9, i] = 6.0 * _C3_A * xi * yi, 3.0 * _C3_A * c1, 0.0
            bx[10, i], by[10, i], bz[10, i] = 2.0 * _C3_Z * yi * zi, 2.0 * _C3_Z * xi * zi, _C3_Z * s1
            bx[11, i], by[11, i], bz[11, i] = 0.0, tmp_c, 2.0 * _C3_Z2[0] * zi * yi
            bx[12, i], by[12, i], bz[12, i] = 0.0, 0.0, 3.0 * _C3_ZZZ[0] * zz + _C3_ZZZ[1]
            bx[13, i], by[13, i], bz[13, i] = tmp_c, 0.0, 2.0 * _C3_Z2[0] * zi * xi
            bx[14, i], by[14, i], bz[14, i] = 2.0 * _C3_Z * zi * xi, -2.0 * _C3_Z * zi * yi, _C3_Z * c1
            bx[15, i], by[15, i], bz[15, i] = 3.0 * _C3_A * c1, -6.0 * _C3_A * xi * yi, 0.0


@njit(inline="always", **_OPTS)
def _block_coefficients(n_bases, sh, m, out) -> None:
    """out [k, c, i] = sh [i, k, c] for a block of m Gaussians: each coefficient laid out along the block."""
    for k in range(n_bases):
        for c in range(3):
            for i in range(m):
                out[k, c, i] = sh[i, k, c]


@njit(inline="always", **_OPTS)
def _sh_values(n_bases, m, b, coef, total) -> None:
    """total [c, i] = sum_k b [k, i] coef [k, c, i], summed over k in order."""
    for c in range(3):
        for i in range(m):
            total[c, i] = 0.0
    for k in range(n_bases):
        for c in range(3):
            for i in range(m):
                total[c, i] += b[k, i] * coef[k, c, i]


@njit(**_OPTS)
def sh_forward(lo, hi, n_bases, sh, points, origins, colour, out) -> None:
    """out[r, g, c] = sum_k basis_k(unit(points[r or 0, g] - origins[r])) sh[g, k, c] for the Gaussians of blocks
    lo..hi-1; with `colour`, max(that + 0.5, 0) (3DGS's colour, NaN kept). out [R, N, 3]."""
    n = sh.shape[0]
    b = np.empty((16, BLOCK))
    x, y, z, norm = np.empty(BLOCK), np.empty(BLOCK), np.empty(BLOCK), np.empty(BLOCK)
    coef = np.empty((16, 3, BLOCK))
    total = np.empty((3, BLOCK))
    for block in range(lo, hi):
        g0 = block * BLOCK
        m = min(BLOCK, n - g0)
        _block_coefficients(n_bases, sh[g0 : g0 + m], m, coef)
        for r in range(origins.shape[0]):
            p = r if points.shape[0] > 1 else 0
            _directions(points[p, g0 : g0 + m], origins[r], m, x, y, z, norm)
            _bases(n_bases, m, x, y, z, b, b, b, b, False)
            _sh_values(n_bases, m, b, coef, total)
            out_r = out[r, g0 : g0 + m]
            for i in range(m):
                for c in range(3):
                    value = total[c, i]
                    if colour:
                        value += 0.5
                        value = 0.0 if value < 0.0 else value
                    out_r[i, c] = value


@njit(**_OPTS)
def sh_backward(lo, hi, n_bases, sh, points, origins, colour, v_out, v_sh, v_points, v_origins) -> None:
    """VJP of `sh_forward` for blocks lo..hi-1: writes v_sh [N, K, 3] (the first K = n_bases), v_points [P, N, 3] (summed
    over rows when P = 1) and v_origins [blocks, R, 3], each block's sum over its Gaussians (the caller sums blocks).
    With `colour`, the gradient passes where SH + 0.5 >= 0, as torch's clamp_min."""
    n = sh.shape[0]
    n_rows = origins.shape[0]
    shared = points.shape[0] == 1
    b = np.empty((16, BLOCK))
    bx = np.empty((16, BLOCK))
    by = np.empty((16, BLOCK))
    bz = np.empty((16, BLOCK))
    x, y, z, norm = np.empty(BLOCK), np.empty(BLOCK), np.empty(BLOCK), np.empty(BLOCK)
    coef = np.empty((16, 3, BLOCK))
    v_coef = np.empty((16, 3, BLOCK))
    total = np.empty((3, BLOCK))
    v_value = np.empty((3, BLOCK))
    vx, vy, vz = np.empty(BLOCK), np.empty(BLOCK), np.empty(BLOCK)
    v_point = np.empty((3, BLOCK))
    for block in range(lo, hi):
        g0 = block * BLOCK
        m = min(BLOCK, n - g0)
        _block_coefficients(n_bases, sh[g0 : g0 + m], m, coef)
        for k in range(n_bases):
            for c in range(3):
                for i in range(m):
                    v_coef[k, c, i] = 0.0
        for c in range(3):
            for i in range(m):
                v_point[c, i] = 0.0
        for r in range(n_rows):
            p = 0 if shared else r
            _directions(points[p, g0 : g0 + m], origins[r], m, x, y, z, norm)
            _bases(n_bases, m, x, y, z, b, bx, by, bz, True)
            v_out_r = v_out[r, g0 : g0 + m]
            if colour:
                _sh_values(n_bases, m, b, coef, total)
                for i in range(m):
                    for c in range(3):
                        v_value[c, i] = v_out_r[i, c] if total[c, i] + 0.5 >= 0.0 else 0.0
            else:
                for i in range(m):
                    for c in range(3):
                        v_value[c, i] = v_out_r[i, c]
            for i in range(m):
                vx[i] = 0.0
                vy[i] = 0.0
                vz[i] = 0.0
            for k in range(n_bases):
                for c in range(3):
                    for i in range(m):
                        v_coef[k, c, i] += v_value[c, i] * b[k, i]
                for i in range(m):
                    v_basis = 0.0
                    v_basis += v_value[0, i] * coef[k, 0, i]
                    v_basis += v_value[1, i] * coef[k, 1, i]
                    v_basis += v_value[2, i] * coef[k, 2, i]
                    vx[i] += v_basis * bx[k, i]
                    vy[i] += v_basis * by[k, i]
                    vz[i] += v_basis * bz[k, i]
            # Through d / max(|d|, eps): the radial part projected out, unless the floor is what divides.
            for i in range(m):
                if norm[i] > NORMALIZE_EPS:
                    radial = x[i] * vx[i] + y[i] * vy[i] + z[i] * vz[i]
                    vx[i] = (vx[i] - x[i] * radial) / norm[i]
                    vy[i] = (vy[i] - y[i] * radial) / norm[i]
                    vz[i] = (vz[i] - z[i] * radial) / norm[i]
                else:
                    vx[i] = vx[i] / NORMALIZE_EPS
                    vy[i] = vy[i] / NORMALIZE_EPS
                    vz[i] = vz[i] / NORMALIZE_EPS
            o0 = o1 = o2 = 0.0
            for i in range(m):
                o0 -= vx[i]
                o1 -= vy[i]
                o2 -= vz[i]
            v_origins[block, r, 0] = o0
            v_origins[block, r, 1] = o1
            v_origins[block, r, 2] = o2
            if shared:
                for i in range(m):
                    v_point[0, i] += vx[i]
                    v_point[1, i] += vy[i]
                    v_point[2, i] += vz[i]
            else:
                v_points_r = v_points[r, g0 : g0 + m]
                for i in range(m):
                    v_points_r[i, 0] = vx[i]
                    v_points_r[i, 1] = vy[i]
                    v_points_r[i, 2] = vz[i]
        if shared:
            v_points_0 = v_points[0, g0 : g0 + m]
            for i in range(m):
                for c in range(3):
                    v_points_0[i, c] = v_point[c, i]
        v_sh_block = v_sh[g0 : g0 + m]
        for k in range(n_bases):
            for c in range(3):
                for i in range(m):
                    v_sh_block[i, k, c] = v_coef[k, c, i]
