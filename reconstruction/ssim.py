"""SSIM of image batches: the per-pixel map with an analytic gradient, fused in numba on CPU. The training
loss uses the zero-padded map; `metrics.ssim` crops it to the pixels whose window lies inside the image.

Autograd through SSIM's torch ops (five depthwise blurs of 1x11 and 11x1 kernels, then the map's
elementwise graph, each op a pass over memory) was a large part of a Stage-II iteration,
most of it in torch's depthwise conv2d blurring the five moments (benchmarks/results/profile.md). The kernels
below take one (view, channel) plane per task, blur with tap-outer, pixel-inner loops over
zero-padded rows (contiguous multiply-adds numba vectorises) and do the elementwise algebra in the
same pass.

With m = blur(x), e_xx = blur(x^2), e_xy = blur(x y), A1 = 2 m_x m_y + C1, A2 = 2 (e_xy - m_x m_y) + C2,
B1 = m_x^2 + m_y^2 + C1, B2 = e_xx - m_x^2 + e_yy - m_y^2 + C2, D = B1 B2 and S = A1 A2 / D:
dS/dm_x = (2 m_y (A2 - A1) - 2 m_x S (B2 - B1)) / D, dS/de_xx = -S B1 / D, dS/de_xy = 2 A1 / D, and for
an upstream gradient G of the map, dL/dx = blur(G dS/dm_x) + 2 x blur(G dS/de_xx) + y blur(G dS/de_xy):
the zero-padded blur with a symmetric kernel is its own adjoint. y alike, with x and y swapped.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from numba import njit
from torch.autograd.function import once_differentiable

from reconstruction.parallel import parallel_for

C1, C2 = 0.01**2, 0.03**2
_OPTS = {"cache": True, "nogil": True, "fastmath": True, "error_model": "numpy"}


def gaussian_window(size: int, sigma: float, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Normalised 1D Gaussian [size], centred at (size - 1) / 2."""
    x = torch.arange(size, dtype=dtype) - (size - 1) / 2
    g = torch.exp(-(x * x) / (2 * sigma * sigma))
    return g / g.sum()


@njit(inline="always", **_OPTS)
def _row_pass(line, g, row):
    """row [W] = line [W + K - 1] (a zero-padded row) correlated with g [K]."""
    w = row.shape[0]
    if g.shape[0] == 11:
        # The training window, unrolled: each output is 11 multiply-adds in registers and one store, where
        # a pass per tap loads and stores the whole row 11 times (benchmarks/results/profile.md).
        g0, g1, g2, g3, g4, g5, g6, g7, g8, g9, g10 = g[0], g[1], g[2], g[3], g[4], g[5], g[6], g[7], g[8], g[9], g[10]
        for x in range(w):
            row[x] = (
                g0 * line[x]
                + g1 * line[x + 1]
                + g2 * line[x + 2]
                + g3 * line[x + 3]
                + g4 * line[x + 4]
                + g5 * line[x + 5]
                + g6 * line[x + 6]
                + g7 * line[x + 7]
                + g8 * line[x + 8]
                + g9 * line[x + 9]
                + g10 * line[x + 10]
            )
        return
    for x in range(w):
        row[x] = g[0] * line[x]
    for j in range(1, g.shape[0]):
        gj = g[j]
        for x in range(w):
            row[x] += gj * line[x + j]


@njit(inline="always", **_OPTS)
def _column_pass(rows, g, dst):
    """dst [H, W] = rows [H + K - 1, W] (row-blurred, zero-padded rows) correlated with g [K] along H."""
    h, w = dst.shape
    if g.shape[0] == 11:
        g0, g1, g2, g3, g4, g5, g6, g7, g8, g9, g10 = g[0], g[1], g[2], g[3], g[4], g[5], g[6], g[7], g[8], g[9], g[10]
        for y in range(h):
            out = dst[y]
            r0, r1, r2, r3, r4, r5 = rows[y], rows[y + 1], rows[y + 2], rows[y + 3], rows[y + 4], rows[y + 5]
            r6, r7, r8, r9, r10 = rows[y + 6], rows[y + 7], rows[y + 8], rows[y + 9], rows[y + 10]
            for x in range(w):
                out[x] = (
                    g0 * r0[x]
                    + g1 * r1[x]
                    + g2 * r2[x]
                    + g3 * r3[x]
                    + g4 * r4[x]
                    + g5 * r5[x]
                    + g6 * r6[x]
                    + g7 * r7[x]
                    + g8 * r8[x]
                    + g9 * r9[x]
                    + g10 * r10[x]
                )
        return
    for y in range(h):
        out = dst[y]
        for x in range(w):
            out[x] = g[0] * rows[y, x]
        for j in range(1, g.shape[0]):
            gj = g[j]
            row = rows[y + j]
            for x in range(w):
                out[x] += gj * row[x]


@njit(inline="always", **_OPTS)
def _blur(src, g, line, rows, dst):
    """dst [H, W] = src [H, W] blurred along W then H; line [W + K - 1] and rows [H + K - 1, W] are
    scratch whose padding stays zero."""
    h, w = src.shape
    r = g.shape[0] // 2
    for y in range(h):
        line[r : r + w] = src[y]
        _row_pass(line, g, rows[y + r])
    _column_pass(rows, g, dst)


@njit(**_OPTS)
def _ssim_forward(lo, hi, x, y, g, s, moments, sums):
    """Planes [lo, hi) of x, y [P, H, W]: the SSIM map s [P, H, W], the blurred moments [P, 5, H, W]
    (m_x, m_y, e_xx, e_yy, e_xy) the backward reuses, and per plane sums [P, 2] = (sum of the map, sum |x - y|),
    accumulated in float64."""
    _, h, w = x.shape
    r = g.shape[0] // 2
    lines = np.zeros((5, w + 2 * r), x.dtype)
    rows = np.zeros((5, h + 2 * r, w), x.dtype)
    for p in range(lo, hi):
        xp, yp, mp = x[p], y[p], moments[p]
        for yy in range(h):
            a, b = xp[yy], yp[yy]
            for k in range(w):
                lines[0, r + k] = a[k]
                lines[1, r + k] = b[k]
                lines[2, r + k] = a[k] * a[k]
                lines[3, r + k] = b[k] * b[k]
                lines[4, r + k] = a[k] * b[k]
            for q in range(5):
                _row_pass(lines[q], g, rows[q, yy + r])
        for q in range(5):
            _column_pass(rows[q], g, mp[q])
        sp = s[p]
        map_sum = 0.0
        l1_sum = 0.0
        for yy in range(h):
            mx, my, exx, eyy, exy = mp[0, yy], mp[1, yy], mp[2, yy], mp[3, yy], mp[4, yy]
            out, a, b = sp[yy], xp[yy], yp[yy]
            row_map = 0.0
            row_l1 = 0.0
            for k in range(w):
                mxy, mxx, myy = mx[k] * my[k], mx[k] * mx[k], my[k] * my[k]
                a1, a2 = 2 * mxy + C1, 2 * (exy[k] - mxy) + C2
                b1, b2 = mxx + myy + C1, exx[k] - mxx + eyy[k] - myy + C2
                out[k] = a1 * a2 / (b1 * b2)
                row_map += out[k]
                row_l1 += abs(a[k] - b[k])
            map_sum += row_map
            l1_sum += row_l1
        sums[p, 0] = map_sum
        sums[p, 1] = l1_sum


@njit(**_OPTS)
def _ssim_backward(lo, hi, x, y, g, moments, grad, map_weight, l1_weight, want_x, want_y, gx, gy):
    """Planes [lo, hi): gx, gy [P, H, W] = the gradients of sum(grad * SSIM map) (module docstring), or with grad of
    shape [0, 0, 0] of map_weight * sum(SSIM map); plus l1_weight * sum |x - y|."""
    constant = grad.shape[0] == 0
    _, h, w = x.shape
    r = g.shape[0] // 2
    line = np.zeros(w + 2 * r, x.dtype)
    rows = np.zeros((h + 2 * r, w), x.dtype)
    partial = np.empty((4, h, w), x.dtype)  # G dS/de_xy, G dS/de_xx (= dS/de_yy), G dS/dm_x, G dS/dm_y
    blurred = np.empty((4, h, w), x.dtype)
    for p in range(lo, hi):
        mp = moments[p]
        for yy in range(h):
            mx, my, exx, eyy, exy = mp[0, yy], mp[1, yy], mp[2, yy], mp[3, yy], mp[4, yy]
            for k in range(w):
                mxy, mxx, myy = mx[k] * my[k], mx[k] * mx[k], my[k] * my[k]
                a1, a2 = 2 * mxy + C1, 2 * (exy[k] - mxy) + C2
                b1, b2 = mxx + myy + C1, exx[k] - mxx + eyy[k] - myy + C2
                gd = (map_weight if constant else grad[p, yy, k]) / (b1 * b2)
                s = a1 * a2 / (b1 * b2)
                da, db = 2 * (a2 - a1) * gd, 2 * (b2 - b1) * s * gd
                partial[0, yy, k] = 2 * a1 * gd
                partial[1, yy, k] = -s * b1 * gd
                partial[2, yy, k] = my[k] * da - mx[k] * db
                partial[3, yy, k] = mx[k] * da - my[k] * db
        for q in range(4):
            if (q == 2 and not want_x) or (q == 3 and not want_y):
                continue
            _blur(partial[q], g, line, rows, blurred[q])
        xp, yp = x[p], y[p]
        for yy in range(h):
            a, b, b_xy, b_sq = xp[yy], yp[yy], blurred[0, yy], blurred[1, yy]
            if want_x:
                out, b_m = gx[p, yy], blurred[2, yy]
                for k in range(w):
                    d = a[k] - b[k]
                    sign = 1.0 if d > 0.0 else (-1.0 if d < 0.0 else 0.0)
                    out[k] = b_m[k] + 2 * a[k] * b_sq[k] + b[k] * b_xy[k] + l1_weight * sign
            if want_y:
                out, b_m = gy[p, yy], blurred[3, yy]
                for k in range(w):
                    d = a[k] - b[k]
                    sign = 1.0 if d > 0.0 else (-1.0 if d < 0.0 else 0.0)
                    out[k] = b_m[k] + 2 * b[k] * b_sq[k] + a[k] * b_xy[k] - l1_weight * sign


@njit(**{**_OPTS, "fastmath": False})
def _gather_windows(lo, hi, src, corners, planes):
    """Planes [lo, hi) of planes [3C, h, w] = each view's window of src [C, H, W, 3], channel-major: plane 3c + k
    is channel k of view c's window, whose top-left corner is corners [C, 2] (y0, x0)."""
    _, h, w = planes.shape
    for p in range(lo, hi):
        c, k = p // 3, p % 3
        y0, x0 = corners[c, 0], corners[c, 1]
        out, view = planes[p], src[c]
        for y in range(h):
            row, dst = view[y0 + y], out[y]
            for x in range(w):
                dst[x] = row[x0 + x, k]


@njit(**{**_OPTS, "fastmath": False})
def _scatter_windows(lo, hi, planes, corners, dst):
    """Views [lo, hi) of dst [C, H, W, 3]: zero, with each view's window set from planes [3C, h, w] (the adjoint of
    `_gather_windows`)."""
    _, h, w = planes.shape
    for c in range(lo, hi):
        view = dst[c]
        view[:] = 0.0
        y0, x0 = corners[c, 0], corners[c, 1]
        for k in range(3):
            src = planes[3 * c + k]
            for y in range(h):
                row, line = view[y0 + y], src[y]
                for x in range(w):
                    row[x0 + x, k] = line[x]


def _planes(t: torch.Tensor) -> torch.Tensor:
    """[C, H, W, 3] -> contiguous [3C, H, W] (one plane per view and channel)."""
    return t.detach().permute(0, 3, 1, 2).reshape(-1, *t.shape[1:3]).contiguous()


def _window_planes(t: torch.Tensor, corners: np.ndarray, height: int, width: int) -> torch.Tensor:
    """[C, H, W, 3] -> contiguous [3C, height, width]: each view's window (corners [C, 2] (y0, x0)), one copy."""
    t = t.detach().contiguous()
    planes = torch.empty((3 * t.shape[0], height, width), dtype=t.dtype)
    parallel_for(_gather_windows, len(planes), t.numpy(), corners, planes.numpy(), grain=3)
    return planes


def _forward_planes(a: torch.Tensor, b: torch.Tensor, g: torch.Tensor, windows: tuple | None = None) -> tuple:
    """(x, y planes [3C, H, W], the map [3C, H, W], moments [3C, 5, H, W], per-plane sums [3C, 2]) of [C, H, W, 3];
    with windows (corners [C, 2], height, width), of each view's window only."""
    x, y = (_planes(a), _planes(b)) if windows is None else (_window_planes(a, *windows), _window_planes(b, *windows))
    s = torch.empty_like(x)
    moments = torch.empty((len(x), 5, *x.shape[1:]), dtype=x.dtype)
    sums = np.empty((len(x), 2))
    parallel_for(_ssim_forward, len(x), x.numpy(), y.numpy(), g.numpy(), s.numpy(), moments.numpy(), sums)
    return x, y, s, moments, sums


def _backward_planes(ctx, grad: torch.Tensor | None, map_weight: float, l1_weight: float):
    """The inputs' gradients [C, H, W, 3] from the planes `_forward_planes` saved in ctx."""
    x, y, g, moments = ctx.saved_tensors
    want_x, want_y = ctx.needs_input_grad[:2]
    gx, gy = torch.empty_like(x), torch.empty_like(x)
    grad = x.new_empty((0, 0, 0)) if grad is None else grad.to(x.dtype).reshape(x.shape).contiguous()
    # The weights in the planes' dtype: a Python float would make numba carry a float32 backward in float64.
    scalar = x.numpy().dtype.type
    parallel_for(
        _ssim_backward,
        len(x),
        x.numpy(),
        y.numpy(),
        g.numpy(),
        moments.numpy(),
        grad.numpy(),
        scalar(map_weight),
        scalar(l1_weight),
        want_x,
        want_y,
        gx.numpy(),
        gy.numpy(),
    )
    c, h, w, _ = ctx.layout
    if ctx.windows is None:
        back = lambda t: t.reshape(c, 3, h, w).permute(0, 2, 3, 1)  # noqa: E731
    else:

        def back(t: torch.Tensor) -> torch.Tensor:
            out = torch.empty(ctx.layout, dtype=t.dtype)
            parallel_for(_scatter_windows, c, t.numpy(), ctx.windows[0], out.numpy())
            return out

    return back(gx) if want_x else None, back(gy) if want_y else None, None


class _SSIMMap(torch.autograd.Function):
    @staticmethod
    def forward(ctx, a: torch.Tensor, b: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        x, y, s, moments, _ = _forward_planes(a, b, g)
        ctx.save_for_backward(x, y, g, moments)
        ctx.layout, ctx.windows = a.shape, None
        return s.reshape(a.shape[0], 3, *a.shape[1:3])

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: torch.Tensor):
        return _backward_planes(ctx, grad, 0.0, 0.0)


class _DSSIMAndL1Sums(torch.autograd.Function):
    """(sum of 1 - SSIM map, sum |a - b|) in the map's one pass, and their gradients in its backward's: the training
    loss needs only these sums, and as torch ops the L1 and the map's sum were ~8 more passes over the batch. The sums
    are taken in float64 (1 - SSIM is small where the fit is good: subtracting a float32 sum from the count would
    cancel its digits).

    With windows (corners [C, 2] (y0, x0), height, width), the sums run over each view's window of a and b, read
    straight from the images, and the gradients are zero outside the windows: one pass each way where cropping
    and then laying out planes copied every image twice (and their gradients twice back)."""

    @staticmethod
    def forward(ctx, a: torch.Tensor, b: torch.Tensor, g: torch.Tensor, windows: tuple | None):
        x, y, s, moments, sums = _forward_planes(a, b, g, windows)
        ctx.save_for_backward(x, y, g, moments)
        ctx.layout, ctx.windows = a.shape, windows
        map_sum, l1_sum = sums.sum(0)
        return a.new_tensor(s.numel() - map_sum), a.new_tensor(l1_sum)

    @staticmethod
    @once_differentiable
    def backward(ctx, g_dssim: torch.Tensor | None, g_l1: torch.Tensor | None):
        grads = _backward_planes(ctx, None, 0.0 if g_dssim is None else -float(g_dssim), 0.0 if g_l1 is None else float(g_l1))
        return *grads, None


def _ssim_map_torch(a: torch.Tensor, b: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """The same map through torch ops and autograd (tensors on a GPU, or dtypes the kernels do not take)."""
    x, y = a.permute(0, 3, 1, 2), b.permute(0, 3, 1, 2)
    ch, r = x.shape[1], len(g) // 2

    def blur(t):
        t = F.conv2d(t, g.reshape(1, 1, 1, -1).expand(ch, 1, 1, -1), padding=(0, r), groups=ch)
        return F.conv2d(t, g.reshape(1, 1, -1, 1).expand(ch, 1, -1, 1), padding=(r, 0), groups=ch)

    mx, my = blur(x), blur(y)
    sxx, syy, sxy = blur(x * x) - mx * mx, blur(y * y) - my * my, blur(x * y) - mx * my
    return ((2 * mx * my + C1) * (2 * sxy + C2)) / ((mx * mx + my * my + C1) * (sxx + syy + C2))


def _prepared(a: torch.Tensor, b: torch.Tensor, window: int, sigma: float) -> tuple:
    """(a, b in their common dtype, the window [window], whether the numba kernels take them)."""
    if window < 1 or window % 2 == 0:
        raise ValueError(f"the SSIM window must be a positive odd number of pixels, got {window}")
    dtype = torch.promote_types(a.dtype, b.dtype)
    a, b = a.to(dtype), b.to(dtype)
    g = gaussian_window(window, sigma, dtype).to(a.device)
    return a, b, g, not a.is_cuda and dtype in (torch.float32, torch.float64)


def ssim_map(a: torch.Tensor, b: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Per-pixel SSIM [C, 3, H, W] of images a, b [C, H, W, 3] (Gaussian window, zero padding at the
    borders, as 3DGS), differentiable in both."""
    a, b, g, fused = _prepared(a, b, window, sigma)
    return _SSIMMap.apply(a, b, g) if fused else _ssim_map_torch(a, b, g)


def dssim_l1_sums(
    a: torch.Tensor, b: torch.Tensor, window: int = 11, sigma: float = 1.5, windows: tuple[torch.Tensor, int, int] | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """(sum of 1 - `ssim_map`, sum |a - b|) of images a, b [C, H, W, 3], differentiable in both: the training loss's
    two terms in one pass each way on CPU.

    windows, optional: (corners [C, 2] int (y0, x0), height, width), the sums of each view's window of the images
    instead (the map zero-padded at the windows' edges), as if a and b were cropped to them first."""
    a, b, g, fused = _prepared(a, b, window, sigma)
    if windows is not None:
        corners, height, width = windows
        if fused:
            return _DSSIMAndL1Sums.apply(a, b, g, (np.ascontiguousarray(corners.numpy(), np.int64), int(height), int(width)))
        a, b = _crop(a, corners, height, width), _crop(b, corners, height, width)
    if fused:
        return _DSSIMAndL1Sums.apply(a, b, g, None)
    return (1 - _ssim_map_torch(a, b, g)).sum(), (a - b).abs().sum()


def _crop(t: torch.Tensor, corners: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """t [C, H, W, 3] cut to each view's window [C, height, width, 3] (differentiable; tensors on a GPU)."""
    return torch.stack([t[c, y : y + height, x : x + width] for c, (y, x) in enumerate(corners.tolist())])
