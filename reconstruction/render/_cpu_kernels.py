"""Numba CPU kernels of the rasterizer: projection, tile binning, compositing and their VJPs.

Geometry and compositing run in float64 whatever the input dtype: a float32 pixel-space mean near
x = 500 px is off by up to 3e-5 px, which alone moves a sharp splat's alpha by more than the 1e-5 the
rasterizer promises. Kernels take numpy arrays and write into preallocated outputs. Parallel loops run
over fixed chunks (of Gaussians) or balanced bins (of tiles), and every sum is taken in an order that
does not depend on the thread count, so results are bit-identical on 2 or 64 threads.

Conventions shared by all kernels:
- conic (a, b, c) is the inverse 2D covariance [[a, b], [b, c]]; sigma = 0.5 (a dx^2 + c dy^2) + b dx dy
  with (dx, dy) = pixel centre - mean2d.
- A Gaussian is visible in a camera iff its radius_x > 0 (projection culls with both radii zero).
- rects [C, N, 4] are inclusive pixel ranges (u_lo, u_hi, v_lo, v_hi) of the pixel centres inside the
  radius box, clipped to the image; tiles follow as pixel // tile_size.
- keys [n_isect] are int64 (float32 depth bits << 32 | gaussian index), sorted within each tile, so the
  order is by depth with ties broken by index; tile t owns keys[tile_offsets[t]:tile_offsets[t + 1]].
- A "slot" is one (camera, Gaussian, tile) intersection, laid out Gaussian-major:
  gauss_offsets[c * N + g] + row-major index of the tile inside the Gaussian's tile rectangle. Kernels
  that run per tile write per-slot partial results, and a per-Gaussian pass sums them, which needs no
  atomics.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

ALPHA_THRESHOLD = 1.0 / 255.0
ALPHA_MAX = 0.999
TRANSMITTANCE_MIN = 1e-4
# Row spans are solved in closed form; widening them by this much (in pixels) keeps every pixel whose
# own alpha test passes, and the per-pixel test stays the authority.
_SPAN_MARGIN = 1e-6
# Fixed chunk counts make the order of floating-point sums independent of the thread count.
GAUSSIAN_CHUNKS = 256
_BINNING_CHUNKS = 64
_KEY_INDEX_MASK = 0xFFFFFFFF

_OPTS = {"cache": True, "error_model": "numpy"}


@njit(**_OPTS)
def _chunk_bounds(chunk: int, n_chunks: int, n: int) -> tuple[int, int]:
    return chunk * n // n_chunks, (chunk + 1) * n // n_chunks


@njit(**_OPTS)
def _rotation_and_factor(quat, scale, rot, factor) -> float:
    """Writes R(q / |q|) into rot [3, 3] and M = R diag(scale) into factor [3, 3]; returns |q|."""
    norm = math.sqrt(np.float64(quat[0]) ** 2 + np.float64(quat[1]) ** 2 + np.float64(quat[2]) ** 2 + np.float64(quat[3]) ** 2)
    w = quat[0] / norm
    x = quat[1] / norm
    y = quat[2] / norm
    z = quat[3] / norm
    rot[0, 0] = 1.0 - 2.0 * (y * y + z * z)
    rot[0, 1] = 2.0 * (x * y - w * z)
    rot[0, 2] = 2.0 * (x * z + w * y)
    rot[1, 0] = 2.0 * (x * y + w * z)
    rot[1, 1] = 1.0 - 2.0 * (x * x + z * z)
    rot[1, 2] = 2.0 * (y * z - w * x)
    rot[2, 0] = 2.0 * (x * z - w * y)
    rot[2, 1] = 2.0 * (y * z + w * x)
    rot[2, 2] = 1.0 - 2.0 * (x * x + y * y)
    for i in range(3):
        for j in range(3):
            factor[i, j] = rot[i, j] * np.float64(scale[j])
    return norm


@njit(**_OPTS)
def _covariance(factor, cov) -> None:
    """cov = M M^T."""
    for i in range(3):
        for j in range(3):
            cov[i, j] = factor[i, 0] * factor[j, 0] + factor[i, 1] * factor[j, 1] + factor[i, 2] * factor[j, 2]


@njit(**_OPTS)
def _to_camera(viewmat, mean, cov, tmp, cov_cam) -> tuple[float, float, float]:
    """Camera-frame mean R m + t (returned) and covariance R cov R^T (written to cov_cam)."""
    # Widen first: float32 * float32 stays float32 in numba (and so does float() of a float32).
    x, y, z = np.float64(mean[0]), np.float64(mean[1]), np.float64(mean[2])
    mx = np.float64(viewmat[0, 0]) * x + np.float64(viewmat[0, 1]) * y + np.float64(viewmat[0, 2]) * z + np.float64(viewmat[0, 3])
    my = np.float64(viewmat[1, 0]) * x + np.float64(viewmat[1, 1]) * y + np.float64(viewmat[1, 2]) * z + np.float64(viewmat[1, 3])
    mz = np.float64(viewmat[2, 0]) * x + np.float64(viewmat[2, 1]) * y + np.float64(viewmat[2, 2]) * z + np.float64(viewmat[2, 3])
    for i in range(3):
        for j in range(3):
            tmp[i, j] = viewmat[i, 0] * cov[0, j] + viewmat[i, 1] * cov[1, j] + viewmat[i, 2] * cov[2, j]
    for i in range(3):
        for j in range(3):
            cov_cam[i, j] = tmp[i, 0] * viewmat[j, 0] + tmp[i, 1] * viewmat[j, 1] + tmp[i, 2] * viewmat[j, 2]
    return mx, my, mz


@njit(**_OPTS)
def _clamp_limits(fx: float, fy: float, cx: float, cy: float, width: int, height: int):
    """gsplat's limits on x/z and y/z: the image plus 30% of the half field of view on each side."""
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    return (
        -(cx / fx + 0.3 * tan_fovx),
        (width - cx) / fx + 0.3 * tan_fovx,
        -(cy / fy + 0.3 * tan_fovy),
        (height - cy) / fy + 0.3 * tan_fovy,
    )


@njit(**_OPTS)
def _jacobian(mx, my, mz, fx, fy, x_lo, x_hi, y_lo, y_hi):
    """Non-zero entries (j00, j02, j11, j12) of the perspective Jacobian, with x/z and y/z clamped.

    The clamp keeps Gaussians far outside the view (and those straddling the near plane) from getting
    unbounded screen-space covariances; the clamped coordinate then follows z, not x or y.
    """
    rz = 1.0 / mz
    tx = mz * min(x_hi, max(x_lo, mx * rz))
    ty = mz * min(y_hi, max(y_lo, my * rz))
    return fx * rz, -fx * tx * rz * rz, fy * rz, -fy * ty * rz * rz


@njit(**_OPTS)
def _covariance2d(cov_cam, j00, j02, j11, j12, eps2d):
    """J W J^T + eps2d I as (s00, s01, s11)."""
    s00 = j00 * j00 * cov_cam[0, 0] + 2.0 * j00 * j02 * cov_cam[0, 2] + j02 * j02 * cov_cam[2, 2] + eps2d
    s01 = (
        j00 * j11 * cov_cam[0, 1]
        + j00 * j12 * cov_cam[0, 2]
        + j02 * j11 * cov_cam[1, 2]
        + j02 * j12 * cov_cam[2, 2]
    )
    s11 = j11 * j11 * cov_cam[1, 1] + 2.0 * j11 * j12 * cov_cam[1, 2] + j12 * j12 * cov_cam[2, 2] + eps2d
    return s00, s01, s11


@njit(parallel=True, **_OPTS)
def project_forward(
    means, quats, scales, opacities, active, viewmats, Ks, width, height, near, far, eps2d,
    means2d, conics, depths, radii,
) -> None:
    """Projects N Gaussians into C cameras; culled entries keep the zeros they were allocated with.

    Inputs: means [N, 3], quats [N, 4] (wxyz, any norm), scales [N, 3], opacities [N], active [N] bool,
    viewmats [C, 4, 4], Ks [C, 3, 3]. Outputs: means2d [C, N, 2] f64, conics [C, N, 3] f64,
    depths [C, N] f64, radii [C, N, 2] int32.
    """
    n = means.shape[0]
    n_cams = viewmats.shape[0]
    n_chunks = max(1, min(GAUSSIAN_CHUNKS, n))
    for chunk in prange(n_chunks):
        rot = np.empty((3, 3))
        factor = np.empty((3, 3))
        cov = np.empty((3, 3))
        tmp = np.empty((3, 3))
        cov_cam = np.empty((3, 3))
        lo, hi = _chunk_bounds(chunk, n_chunks, n)
        for g in range(lo, hi):
            opacity = np.float64(opacities[g])
            # `not >=` also culls NaN opacities.
            if not active[g] or not opacity >= ALPHA_THRESHOLD:
                continue
            _rotation_and_factor(quats[g], scales[g], rot, factor)
            _covariance(factor, cov)
            # gsplat 1.5.3's opacity-aware box: alpha >= 1/255 needs sigma <= ln(255 opacity).
            extent = math.sqrt(2.0 * math.log(opacity / ALPHA_THRESHOLD))
            for c in range(n_cams):
                mx, my, mz = _to_camera(viewmats[c], means[g], cov, tmp, cov_cam)
                if not (mz > near and mz < far):
                    continue
                fx, fy = np.float64(Ks[c, 0, 0]), np.float64(Ks[c, 1, 1])
                cx, cy = np.float64(Ks[c, 0, 2]), np.float64(Ks[c, 1, 2])
                x_lo, x_hi, y_lo, y_hi = _clamp_limits(fx, fy, cx, cy, width, height)
                j00, j02, j11, j12 = _jacobian(mx, my, mz, fx, fy, x_lo, x_hi, y_lo, y_hi)
                s00, s01, s11 = _covariance2d(cov_cam, j00, j02, j11, j12, eps2d)
                det = s00 * s11 - s01 * s01
                if not det > 0.0:
                    continue
                # Capped so that absurd covariances cannot overflow the integer conversion.
                rx = math.ceil(min(extent * math.sqrt(s00), 1e9))
                ry = math.ceil(min(extent * math.sqrt(s11), 1e9))
                if rx <= 0 or ry <= 0:
                    continue
                u = fx * mx / mz + cx
                v = fy * my / mz + cy
                if u + rx <= 0.0 or u - rx >= width or v + ry <= 0.0 or v - ry >= height:
                    continue
                means2d[c, g, 0] = u
                means2d[c, g, 1] = v
                conics[c, g, 0] = s11 / det
                conics[c, g, 1] = -s01 / det
                conics[c, g, 2] = s00 / det
                depths[c, g] = mz
                radii[c, g, 0] = rx
                radii[c, g, 1] = ry


@njit(parallel=True, **_OPTS)
def project_backward(
    means, quats, scales, viewmats, Ks, width, height, radii, conics, v_means2d, v_conics,
    v_means, v_quats, v_scales, v_viewmats_chunks,
) -> None:
    """VJP of `project_forward` for the visible entries.

    v_means2d [C, N, 2] and v_conics [C, N, 3] (gradients w.r.t. (a, b, c)) come in; v_means [N, 3],
    v_quats [N, 4], v_scales [N, 3] are written (zero-initialised by the caller) and per-chunk viewmat
    gradients are accumulated into v_viewmats_chunks [n_chunks, C, 3, 4] (the caller sums the chunks).
    """
    n = means.shape[0]
    n_cams = viewmats.shape[0]
    n_chunks = v_viewmats_chunks.shape[0]
    for chunk in prange(n_chunks):
        rot = np.empty((3, 3))
        factor = np.empty((3, 3))
        cov = np.empty((3, 3))
        tmp = np.empty((3, 3))
        cov_cam = np.empty((3, 3))
        v_cov = np.empty((3, 3))
        v_w = np.empty((3, 3))
        rw = np.empty((3, 3))
        v_factor = np.empty((3, 3))
        lo, hi = _chunk_bounds(chunk, n_chunks, n)
        for g in range(lo, hi):
            seen = False
            for c in range(n_cams):
                seen = seen or radii[c, g, 0] > 0
            if not seen:
                continue
            qnorm = _rotation_and_factor(quats[g], scales[g], rot, factor)
            _covariance(factor, cov)
            v_cov[:] = 0.0
            vmx_w = 0.0
            vmy_w = 0.0
            vmz_w = 0.0
            for c in range(n_cams):
                if radii[c, g, 0] <= 0:
                    continue
                vm = viewmats[c]
                mx, my, mz = _to_camera(vm, means[g], cov, tmp, cov_cam)
                fx, fy = np.float64(Ks[c, 0, 0]), np.float64(Ks[c, 1, 1])
                cx, cy = np.float64(Ks[c, 0, 2]), np.float64(Ks[c, 1, 2])
                x_lo, x_hi, y_lo, y_hi = _clamp_limits(fx, fy, cx, cy, width, height)
                j00, j02, j11, j12 = _jacobian(mx, my, mz, fx, fy, x_lo, x_hi, y_lo, y_hi)
                a, b, cc = conics[c, g, 0], conics[c, g, 1], conics[c, g, 2]
                # dL/dQ as a symmetric matrix V (b appears twice in Q); dSigma = -Q V Q.
                v00, v01, v11 = v_conics[c, g, 0], 0.5 * v_conics[c, g, 1], v_conics[c, g, 2]
                p00 = a * v00 + b * v01
                p01 = a * v01 + b * v11
                p10 = b * v00 + cc * v01
                p11 = b * v01 + cc * v11
                g00 = -(p00 * a + p01 * b)
                g01 = -(p00 * b + p01 * cc)
                g11 = -(p10 * b + p11 * cc)
                # G J, with J = [[j00, 0, j02], [0, j11, j12]].
                gj00 = g00 * j00
                gj01 = g01 * j11
                gj02 = g00 * j02 + g01 * j12
                gj10 = g01 * j00
                gj11 = g11 * j11
                gj12 = g01 * j02 + g11 * j12
                # dL/dJ = 2 G J W (only the structurally non-zero entries matter).
                vj00 = 2.0 * (gj00 * cov_cam[0, 0] + gj01 * cov_cam[1, 0] + gj02 * cov_cam[2, 0])
                vj02 = 2.0 * (gj00 * cov_cam[0, 2] + gj01 * cov_cam[1, 2] + gj02 * cov_cam[2, 2])
                vj11 = 2.0 * (gj10 * cov_cam[0, 1] + gj11 * cov_cam[1, 1] + gj12 * cov_cam[2, 1])
                vj12 = 2.0 * (gj10 * cov_cam[0, 2] + gj11 * cov_cam[1, 2] + gj12 * cov_cam[2, 2])
                # dL/dW = J^T G J.
                for k in range(3):
                    gj0k = gj00 if k == 0 else (gj01 if k == 1 else gj02)
                    gj1k = gj10 if k == 0 else (gj11 if k == 1 else gj12)
                    v_w[0, k] = j00 * gj0k
                    v_w[1, k] = j11 * gj1k
                    v_w[2, k] = j02 * gj0k + j12 * gj1k
                # Camera-frame mean: through mean2d and through J.
                rz = 1.0 / mz
                rz2 = rz * rz
                rz3 = rz2 * rz
                vu, vv = v_means2d[c, g, 0], v_means2d[c, g, 1]
                vmx = fx * rz * vu
                vmy = fy * rz * vv
                vmz = -(fx * mx * vu + fy * my * vv) * rz2 - fx * rz2 * vj00 - fy * rz2 * vj11
                if x_lo <= mx * rz <= x_hi:
                    vmx += -fx * rz2 * vj02
                    vmz += 2.0 * fx * mx * rz3 * vj02
                else:
                    vmz += fx * (mz * min(x_hi, max(x_lo, mx * rz))) * rz3 * vj02
                if y_lo <= my * rz <= y_hi:
                    vmy += -fy * rz2 * vj12
                    vmz += 2.0 * fy * my * rz3 * vj12
                else:
                    vmz += fy * (mz * min(y_hi, max(y_lo, my * rz))) * rz3 * vj12
                # W = R cov R^T: dL/dcov += R^T v_w R and dL/dR += 2 v_w R cov; m_cam = R m + t.
                for i in range(3):
                    for j in range(3):
                        rw[i, j] = vm[0, i] * v_w[0, j] + vm[1, i] * v_w[1, j] + vm[2, i] * v_w[2, j]
                for i in range(3):
                    for j in range(3):
                        v_cov[i, j] += rw[i, 0] * vm[0, j] + rw[i, 1] * vm[1, j] + rw[i, 2] * vm[2, j]
                for i in range(3):
                    for j in range(3):
                        tmp[i, j] = vm[i, 0] * cov[0, j] + vm[i, 1] * cov[1, j] + vm[i, 2] * cov[2, j]
                vmc = (vmx, vmy, vmz)
                for i in range(3):
                    for j in range(3):
                        v_viewmats_chunks[chunk, c, i, j] += (
                            2.0 * (v_w[i, 0] * tmp[0, j] + v_w[i, 1] * tmp[1, j] + v_w[i, 2] * tmp[2, j])
                            + vmc[i] * means[g, j]
                        )
                    v_viewmats_chunks[chunk, c, i, 3] += vmc[i]
                vmx_w += vm[0, 0] * vmx + vm[1, 0] * vmy + vm[2, 0] * vmz
                vmy_w += vm[0, 1] * vmx + vm[1, 1] * vmy + vm[2, 1] * vmz
                vmz_w += vm[0, 2] * vmx + vm[1, 2] * vmy + vm[2, 2] * vmz
            v_means[g, 0] = vmx_w
            v_means[g, 1] = vmy_w
            v_means[g, 2] = vmz_w
            # cov = M M^T with M = R diag(s): dL/dM = 2 v_cov M.
            for i in range(3):
                for j in range(3):
                    v_factor[i, j] = 2.0 * (v_cov[i, 0] * factor[0, j] + v_cov[i, 1] * factor[1, j] + v_cov[i, 2] * factor[2, j])
            for j in range(3):
                v_scales[g, j] = v_factor[0, j] * rot[0, j] + v_factor[1, j] * rot[1, j] + v_factor[2, j] * rot[2, j]
            # dL/dR, then through R(q) of the unit quaternion, then through the normalisation.
            for i in range(3):
                for j in range(3):
                    v_factor[i, j] *= np.float64(scales[g, j])
            w = quats[g, 0] / qnorm
            x = quats[g, 1] / qnorm
            y = quats[g, 2] / qnorm
            z = quats[g, 3] / qnorm
            r = v_factor
            vw = 2.0 * (-z * r[0, 1] + y * r[0, 2] + z * r[1, 0] - x * r[1, 2] - y * r[2, 0] + x * r[2, 1])
            vx = 2.0 * (
                y * r[0, 1] + z * r[0, 2] + y * r[1, 0] - 2.0 * x * r[1, 1] - w * r[1, 2]
                + z * r[2, 0] + w * r[2, 1] - 2.0 * x * r[2, 2]
            )
            vy = 2.0 * (
                -2.0 * y * r[0, 0] + x * r[0, 1] + w * r[0, 2] + x * r[1, 0] + z * r[1, 2]
                - w * r[2, 0] + z * r[2, 1] - 2.0 * y * r[2, 2]
            )
            vz = 2.0 * (
                -2.0 * z * r[0, 0] - w * r[0, 1] + x * r[0, 2] + w * r[1, 0] - 2.0 * z * r[1, 1]
                + y * r[1, 2] + x * r[2, 0] + y * r[2, 1]
            )
            dot = w * vw + x * vx + y * vy + z * vz
            v_quats[g, 0] = (vw - w * dot) / qnorm
            v_quats[g, 1] = (vx - x * dot) / qnorm
            v_quats[g, 2] = (vy - y * dot) / qnorm
            v_quats[g, 3] = (vz - z * dot) / qnorm


@njit(parallel=True, **_OPTS)
def pixel_rects(means2d, radii, width, height, tile_size, rects, tile_counts) -> None:
    """Pixel range of each visible Gaussian's radius box and the number of tiles it touches.

    A pixel u belongs when its centre u + 0.5 lies in [mean - radius, mean + radius]; the radius box
    holds every pixel with alpha >= 1/255, so no pixel that could be shaded is lost. Writes rects
    [C, N, 4] and tile_counts [C * N] (zero for culled Gaussians and boxes without a pixel centre).
    """
    n_cams, n = radii.shape[0], radii.shape[1]
    for cg in prange(n_cams * n):
        c = cg // n
        g = cg - c * n
        tile_counts[cg] = 0
        if radii[c, g, 0] <= 0:
            continue
        rx, ry = np.float64(radii[c, g, 0]), np.float64(radii[c, g, 1])
        u_lo = max(0, math.ceil(means2d[c, g, 0] - rx - 0.5))
        u_hi = min(width - 1, math.floor(means2d[c, g, 0] + rx - 0.5))
        v_lo = max(0, math.ceil(means2d[c, g, 1] - ry - 0.5))
        v_hi = min(height - 1, math.floor(means2d[c, g, 1] + ry - 0.5))
        if u_lo > u_hi or v_lo > v_hi:
            continue
        rects[c, g, 0] = u_lo
        rects[c, g, 1] = u_hi
        rects[c, g, 2] = v_lo
        rects[c, g, 3] = v_hi
        tile_counts[cg] = (u_hi // tile_size - u_lo // tile_size + 1) * (v_hi // tile_size - v_lo // tile_size + 1)


@njit(parallel=True, **_OPTS)
def bin_and_sort(rects, tile_counts, depth_bits, tile_size, tiles_x, tiles_y):
    """Tile lists sorted by (depth, index): returns (tile_offsets [C * tiles + 1], keys [n_isect]).

    A counting sort by tile (per-chunk histograms, so the scatter needs no atomics) followed by an
    in-place sort of each tile's keys. depth_bits [C * N] int64 are the float32 bit patterns of the
    (positive) depths, which order like the depths themselves.
    """
    n_cams, n = rects.shape[0], rects.shape[1]
    n_total = n_cams * n
    tiles_per_cam = tiles_x * tiles_y
    n_tiles = n_cams * tiles_per_cam
    n_chunks = max(1, min(_BINNING_CHUNKS, n_total))
    hist = np.zeros((n_chunks, n_tiles), np.int64)
    for chunk in prange(n_chunks):
        lo, hi = _chunk_bounds(chunk, n_chunks, n_total)
        for cg in range(lo, hi):
            if tile_counts[cg] == 0:
                continue
            c = cg // n
            g = cg - c * n
            for ty in range(rects[c, g, 2] // tile_size, rects[c, g, 3] // tile_size + 1):
                for tx in range(rects[c, g, 0] // tile_size, rects[c, g, 1] // tile_size + 1):
                    hist[chunk, c * tiles_per_cam + ty * tiles_x + tx] += 1
    tile_offsets = np.empty(n_tiles + 1, np.int64)
    cursor = np.empty((n_chunks, n_tiles), np.int64)
    running = 0
    for t in range(n_tiles):
        tile_offsets[t] = running
        for chunk in range(n_chunks):
            cursor[chunk, t] = running
            running += hist[chunk, t]
    tile_offsets[n_tiles] = running
    keys = np.empty(running, np.int64)
    for chunk in prange(n_chunks):
        lo, hi = _chunk_bounds(chunk, n_chunks, n_total)
        for cg in range(lo, hi):
            if tile_counts[cg] == 0:
                continue
            c = cg // n
            g = cg - c * n
            key = (depth_bits[cg] << 32) | g
            for ty in range(rects[c, g, 2] // tile_size, rects[c, g, 3] // tile_size + 1):
                for tx in range(rects[c, g, 0] // tile_size, rects[c, g, 1] // tile_size + 1):
                    t = c * tiles_per_cam + ty * tiles_x + tx
                    keys[cursor[chunk, t]] = key
                    cursor[chunk, t] += 1
    for t in prange(n_tiles):
        keys[tile_offsets[t] : tile_offsets[t + 1]].sort()
    return tile_offsets, keys


@njit(**_OPTS)
def balance_tiles(tile_offsets, n_bins):
    """Greedy longest-first assignment of tiles to n_bins work bins by intersection count.

    Returns (work [n_tiles] tile ids grouped by bin, work_offsets [n_bins + 1]); prange over bins then
    gives each thread about the same number of pixel-Gaussian pairs, whereas a static split over tiles
    hands the object's tiles to one thread and the empty border to the other.
    """
    n_tiles = tile_offsets.shape[0] - 1
    cost = np.empty(n_tiles, np.int64)
    for t in range(n_tiles):
        cost[t] = tile_offsets[t + 1] - tile_offsets[t] + 1
    order = np.argsort(-cost, kind="mergesort")
    load = np.zeros(n_bins, np.int64)
    owner = np.empty(n_tiles, np.int64)
    size = np.zeros(n_bins + 1, np.int64)
    for t in order:
        best = 0
        for k in range(1, n_bins):
            if load[k] < load[best]:
                best = k
        owner[t] = best
        load[best] += cost[t]
        size[best + 1] += 1
    work_offsets = np.cumsum(size)
    fill = work_offsets[:-1].copy()
    work = np.empty(n_tiles, np.int64)
    for t in order:
        work[fill[owner[t]]] = t
        fill[owner[t]] += 1
    return work, work_offsets


@njit(**_OPTS)
def _row_span(py, mx, my, a, b, det_conic, two_log, col_lo, col_hi):
    """Pixel columns of row py where sigma <= log(255 opacity), clipped to [col_lo, col_hi].

    Solving the quadratic in dx per row visits only pixels inside the ellipse instead of its whole
    bounding box (a 4/pi saving for round splats, far more for thin diagonal ones).
    """
    dy = py + 0.5 - my
    disc = a * two_log - dy * dy * det_conic
    if disc < 0.0:
        return 1, 0
    root = math.sqrt(disc)
    x_lo = mx + (-b * dy - root) / a - 0.5 - _SPAN_MARGIN
    x_hi = mx + (-b * dy + root) / a - 0.5 + _SPAN_MARGIN
    # Clip in float first so that huge spans cannot overflow the integer conversion.
    px0 = max(col_lo, math.ceil(max(x_lo, col_lo - 1.0)))
    px1 = min(col_hi, math.floor(min(x_hi, col_hi + 1.0)))
    return px0, px1


@njit(**_OPTS)
def _tile_geometry(tile, tiles_x, tiles_per_cam, tile_size, width, height):
    c = tile // tiles_per_cam
    local = tile - c * tiles_per_cam
    ty = local // tiles_x
    tx = local - ty * tiles_x
    x0 = tx * tile_size
    y0 = ty * tile_size
    return c, tx, ty, x0, y0, min(width, x0 + tile_size) - 1, min(height, y0 + tile_size) - 1


@njit(**_OPTS)
def _slot(rect, gauss_offset, tx, ty, tile_size) -> int:
    tx0 = rect[0] // tile_size
    ty0 = rect[2] // tile_size
    return gauss_offset + (ty - ty0) * (rect[1] // tile_size - tx0 + 1) + (tx - tx0)


@njit(parallel=True, **_OPTS)
def rasterize_forward(
    means2d, conics, colors, opacities, backgrounds, rects, gauss_offsets, tile_offsets, keys,
    work, work_offsets, width, height, tile_size, tiles_x,
    out_colors, out_transmittance, out_last, slot_counts,
) -> None:
    """Front-to-back alpha compositing, one tile at a time, Gaussian-major inside a tile.

    Each pixel sees its Gaussians in the tile's depth order, exactly as a per-pixel loop would; walking
    Gaussians in the outer loop lets each visit only the pixels inside its own ellipse. Writes
    out_colors [C, H, W, D], out_transmittance [C, H, W] f64 (final T), out_last [C, H, W] int64 (key
    index of the last contributor, -1 if none) and slot_counts [n_isect] (pixels each slot shaded).
    """
    n = means2d.shape[1]
    depth = colors.shape[2]
    tiles_per_cam = tiles_x * ((height + tile_size - 1) // tile_size)
    n_px = tile_size * tile_size
    for bin_ in prange(work_offsets.shape[0] - 1):
        trans = np.empty(n_px)
        acc = np.empty((n_px, depth))
        last = np.empty(n_px, np.int64)
        done = np.empty(n_px, np.bool_)
        for w in range(work_offsets[bin_], work_offsets[bin_ + 1]):
            tile = work[w]
            c, tx, ty, x0, y0, x1, y1 = _tile_geometry(tile, tiles_x, tiles_per_cam, tile_size, width, height)
            trans[:] = 1.0
            acc[:] = 0.0
            last[:] = -1
            done[:] = False
            n_live = (x1 - x0 + 1) * (y1 - y0 + 1)
            for k in range(tile_offsets[tile], tile_offsets[tile + 1]):
                if n_live == 0:
                    break
                g = keys[k] & _KEY_INDEX_MASK
                rect = rects[c, g]
                mx, my = means2d[c, g, 0], means2d[c, g, 1]
                a, b, cc = conics[c, g, 0], conics[c, g, 1], conics[c, g, 2]
                opacity = np.float64(opacities[g])
                two_log = 2.0 * math.log(opacity / ALPHA_THRESHOLD)
                det_conic = a * cc - b * b
                shaded = 0
                for py in range(max(y0, rect[2]), min(y1, rect[3]) + 1):
                    px0, px1 = _row_span(py, mx, my, a, b, det_conic, two_log, max(x0, rect[0]), min(x1, rect[1]))
                    dy = py + 0.5 - my
                    row = (py - y0) * tile_size - x0
                    for px in range(px0, px1 + 1):
                        p = row + px
                        if done[p]:
                            continue
                        dx = px + 0.5 - mx
                        sigma = 0.5 * (a * dx * dx + cc * dy * dy) + b * dx * dy
                        if sigma < 0.0:
                            continue
                        alpha = min(ALPHA_MAX, opacity * math.exp(-sigma))
                        if alpha < ALPHA_THRESHOLD:
                            continue
                        next_t = trans[p] * (1.0 - alpha)
                        if next_t <= TRANSMITTANCE_MIN:
                            done[p] = True
                            n_live -= 1
                            continue
                        weight = alpha * trans[p]
                        for d in range(depth):
                            acc[p, d] += weight * colors[c, g, d]
                        trans[p] = next_t
                        last[p] = k
                        shaded += 1
                slot_counts[_slot(rect, gauss_offsets[c * n + g], tx, ty, tile_size)] = shaded
            for py in range(y0, y1 + 1):
                for px in range(x0, x1 + 1):
                    p = (py - y0) * tile_size + (px - x0)
                    for d in range(depth):
                        out_colors[c, py, px, d] = acc[p, d] + trans[p] * backgrounds[c, d]
                    out_transmittance[c, py, px] = trans[p]
                    out_last[c, py, px] = last[p]


@njit(parallel=True, **_OPTS)
def rasterize_backward(
    means2d, conics, colors, opacities, backgrounds, rects, gauss_offsets, tile_offsets, keys,
    work, work_offsets, width, height, tile_size, tiles_x,
    transmittance, last_ids, v_out_colors, v_out_alphas, slot_grads,
) -> None:
    """Back-to-front VJP of `rasterize_forward` (3DGS): T is recovered by dividing by (1 - alpha).

    v_out_colors [C, H, W, D] and v_out_alphas [C, H, W] come in; slot_grads [n_isect, 6 + D]
    (zero-initialised) receives per-slot d/d(mean2d x, y, conic a, b, c, opacity, colour...).
    """
    n = means2d.shape[1]
    depth = colors.shape[2]
    tiles_per_cam = tiles_x * ((height + tile_size - 1) // tile_size)
    n_px = tile_size * tile_size
    for bin_ in prange(work_offsets.shape[0] - 1):
        trans = np.empty(n_px)
        t_final = np.empty(n_px)
        behind = np.empty((n_px, depth))
        v_px = np.empty((n_px, depth))
        v_t_final = np.empty(n_px)
        last = np.empty(n_px, np.int64)
        v_color = np.empty(depth)
        for w in range(work_offsets[bin_], work_offsets[bin_ + 1]):
            tile = work[w]
            c, tx, ty, x0, y0, x1, y1 = _tile_geometry(tile, tiles_x, tiles_per_cam, tile_size, width, height)
            k_max = -1
            for py in range(y0, y1 + 1):
                for px in range(x0, x1 + 1):
                    p = (py - y0) * tile_size + (px - x0)
                    trans[p] = transmittance[c, py, px]
                    t_final[p] = trans[p]
                    last[p] = last_ids[c, py, px]
                    k_max = max(k_max, last[p])
                    # alpha = 1 - T and colour += T * background both depend on T through T_final.
                    v_t = -v_out_alphas[c, py, px]
                    for d in range(depth):
                        behind[p, d] = 0.0
                        v_px[p, d] = v_out_colors[c, py, px, d]
                        v_t += backgrounds[c, d] * v_px[p, d]
                    v_t_final[p] = v_t
            for k in range(k_max, tile_offsets[tile] - 1, -1):
                g = keys[k] & _KEY_INDEX_MASK
                rect = rects[c, g]
                mx, my = means2d[c, g, 0], means2d[c, g, 1]
                a, b, cc = conics[c, g, 0], conics[c, g, 1], conics[c, g, 2]
                opacity = np.float64(opacities[g])
                two_log = 2.0 * math.log(opacity / ALPHA_THRESHOLD)
                det_conic = a * cc - b * b
                v_mx = 0.0
                v_my = 0.0
                v_a = 0.0
                v_b = 0.0
                v_c = 0.0
                v_opacity = 0.0
                v_color[:] = 0.0
                for py in range(max(y0, rect[2]), min(y1, rect[3]) + 1):
                    px0, px1 = _row_span(py, mx, my, a, b, det_conic, two_log, max(x0, rect[0]), min(x1, rect[1]))
                    dy = py + 0.5 - my
                    row = (py - y0) * tile_size - x0
                    for px in range(px0, px1 + 1):
                        p = row + px
                        if k > last[p]:
                            continue
                        dx = px + 0.5 - mx
                        sigma = 0.5 * (a * dx * dx + cc * dy * dy) + b * dx * dy
                        if sigma < 0.0:
                            continue
                        vis = math.exp(-sigma)
                        raw_alpha = opacity * vis
                        alpha = min(ALPHA_MAX, raw_alpha)
                        if alpha < ALPHA_THRESHOLD:
                            continue
                        inv_one_minus = 1.0 / (1.0 - alpha)
                        trans[p] *= inv_one_minus
                        t_here = trans[p]
                        weight = alpha * t_here
                        v_alpha = -t_final[p] * inv_one_minus * v_t_final[p]
                        for d in range(depth):
                            col = colors[c, g, d]
                            v_color[d] += weight * v_px[p, d]
                            v_alpha += (col * t_here - behind[p, d] * inv_one_minus) * v_px[p, d]
                            behind[p, d] += col * weight
                        # Where min() clamps alpha to 0.999 it no longer depends on opacity or sigma.
                        if raw_alpha <= ALPHA_MAX:
                            v_sigma = -raw_alpha * v_alpha
                            v_a += 0.5 * v_sigma * dx * dx
                            v_b += v_sigma * dx * dy
                            v_c += 0.5 * v_sigma * dy * dy
                            v_mx -= v_sigma * (a * dx + b * dy)
                            v_my -= v_sigma * (b * dx + cc * dy)
                            v_opacity += vis * v_alpha
                s = _slot(rect, gauss_offsets[c * n + g], tx, ty, tile_size)
                slot_grads[s, 0] = v_mx
                slot_grads[s, 1] = v_my
                slot_grads[s, 2] = v_a
                slot_grads[s, 3] = v_b
                slot_grads[s, 4] = v_c
                slot_grads[s, 5] = v_opacity
                for d in range(depth):
                    slot_grads[s, 6 + d] = v_color[d]


@njit(parallel=True, **_OPTS)
def sum_slot_rows(slot_values, gauss_offsets, out) -> None:
    """out[i, :] = sum of slot_values[s, :] over Gaussian i's slots gauss_offsets[i]:gauss_offsets[i + 1]."""
    for i in prange(out.shape[0]):
        for s in range(gauss_offsets[i], gauss_offsets[i + 1]):
            for j in range(out.shape[1]):
                out[i, j] += slot_values[s, j]


@njit(parallel=True, **_OPTS)
def sum_slot_counts(slot_counts, gauss_offsets, out) -> None:
    """out[i] = sum of slot_counts over Gaussian i's slots gauss_offsets[i]:gauss_offsets[i + 1]."""
    for i in prange(out.shape[0]):
        total = 0
        for s in range(gauss_offsets[i], gauss_offsets[i + 1]):
            total += slot_counts[s]
        out[i] = total
