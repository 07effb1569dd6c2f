"""Training losses and the splat-dropout schedule (paper 3.6).

Images are [C, H, W, 3] float32 tensors in [0, 1]; alphas and masks [C, H, W] or [C, H, W, 1]
(masks may be fractional: a mask downsampled by area keeps its edge coverage).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from numba import njit
from scipy import sparse
from torch.autograd.function import once_differentiable

from reconstruction.parallel import parallel_for
from reconstruction.ssim import dssim_l1_sums, ssim_map


def _hw(t: torch.Tensor) -> torch.Tensor:
    return t[..., 0] if t.dim() == 4 else t


@njit(cache=True, nogil=True, error_model="numpy")
def _silhouette_sums(lo, hi, alpha, mask, valid, sums) -> None:
    """Per view c in lo..hi-1: sums[c] = (sum |A - M| over valid pixels, valid pixel count, sum M (1 - A), sum M),
    accumulated in float64. alpha, mask [C, P] float32, valid [C, P] bool or [0, 0] (every pixel)."""
    every = valid.shape[0] == 0
    for c in range(lo, hi):
        l1 = 0.0
        count = 0.0
        under = 0.0
        mass = 0.0
        for i in range(alpha.shape[1]):
            a, m = alpha[c, i], mask[c, i]
            if every or valid[c, i]:
                l1 += abs(a - m)
                count += 1.0
            under += m * (1.0 - a)
            mass += m
        sums[c, 0], sums[c, 1], sums[c, 2], sums[c, 3] = l1, count, under, mass


@njit(cache=True, nogil=True, error_model="numpy")
def _silhouette_grad(lo, hi, alpha, mask, valid, w_l1, w_fill, grad) -> None:
    """grad [C, P] = w_l1 sign(A - M) on valid pixels - w_fill M: the two losses' gradients, weighted."""
    every = valid.shape[0] == 0
    for c in range(lo, hi):
        for i in range(alpha.shape[1]):
            d = alpha[c, i] - mask[c, i]
            sign = 1.0 if d > 0.0 else (-1.0 if d < 0.0 else 0.0)
            grad[c, i] = (w_l1 * sign if every or valid[c, i] else 0.0) - w_fill * mask[c, i]


class _SilhouetteLosses(torch.autograd.Function):
    """(L_mask, L_fill) in one pass over alpha and mask, and their gradient in one more: as torch ops they took ~10
    passes over a 10-view batch's pixels forward and backward (benchmarks/results/profile.md)."""

    @staticmethod
    def forward(ctx, alpha: torch.Tensor, mask: torch.Tensor, valid: torch.Tensor | None):
        n_views = alpha.shape[0]
        a = alpha.detach().contiguous().reshape(n_views, -1).numpy()
        m = mask.detach().contiguous().reshape(n_views, -1).numpy()
        v = np.zeros((0, 0), np.bool_) if valid is None else valid.contiguous().reshape(n_views, -1).numpy()
        # Saved so that autograd notices an in-place change of alpha before the backward reads it.
        ctx.save_for_backward(alpha)
        sums = np.empty((n_views, 4))
        parallel_for(_silhouette_sums, n_views, a, m, v, sums)
        l1, count, under, mass = sums.sum(0)
        ctx.arrays, ctx.shape = (a, m, v), alpha.shape
        ctx.count, ctx.mass = max(count, 1.0), max(mass, 1.0)
        return alpha.new_tensor(l1 / ctx.count), alpha.new_tensor(under / ctx.mass)

    @staticmethod
    @once_differentiable
    def backward(ctx, g_l1: torch.Tensor | None, g_fill: torch.Tensor | None):
        ctx.saved_tensors  # noqa: B018 (the version check)
        a, m, v = ctx.arrays
        w_l1 = 0.0 if g_l1 is None else float(g_l1) / ctx.count
        w_fill = 0.0 if g_fill is None else float(g_fill) / ctx.mass
        grad = np.empty_like(a)
        parallel_for(_silhouette_grad, a.shape[0], a, m, v, w_l1, w_fill, grad)
        return torch.from_numpy(grad).reshape(ctx.shape), None, None


def silhouette_losses(alpha: torch.Tensor, mask: torch.Tensor, valid: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(L_mask, L_fill) of rendered alpha [C, H, W] or [C, H, W, 1] against mask [C, H, W] (or [..., 1]).

    L_mask = mean |A - M| over pixels (eq. mask); with valid [C, H, W] bool, over the pixels each photograph has
    (views of mixed sizes on one canvas), so a splat beyond a photo's edge is not pushed away.
    L_fill = sum M (1 - A) / sum M, the mean under-coverage over the object: it pushes the rendered alpha to
    saturate inside the mask. L_mask spreads its weight over the whole image, so the object's rim pixels (a few %
    of it) stay at alpha 0.5-0.9, and a render composited on white shows them washed out.
    """
    m = _hw(mask).to(alpha.dtype)
    fused = (
        alpha.dtype == torch.float32
        and alpha.device.type == "cpu"
        and not m.requires_grad
        and m.shape == _hw(alpha).shape
        and (valid is None or valid.shape == m.shape)
    )
    if fused:
        return _SilhouetteLosses.apply(alpha, m, valid)
    # Anything else (a GPU, float64, a mask to differentiate or one that broadcasts) through torch ops.
    diff = (_hw(alpha) - m).abs()
    l1 = diff.mean() if valid is None else diff[valid].sum() / valid.sum().clamp_min(1)
    return l1, (m * (1 - _hw(alpha))).sum() / m.sum().clamp_min(1.0)


def mask_l1(alpha: torch.Tensor, mask: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
    """L_mask of `silhouette_losses`."""
    return silhouette_losses(alpha, mask, valid)[0]


def composite_parts(image: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(image * M [C, H, W, 3], 1 - M [C, H, W, 1]): `composite` over background bg is part0 + bg * part1, so a
    training loop that draws a new background every iteration computes the parts once."""
    m = _hw(mask).to(image.dtype)[..., None]
    return image * m, 1 - m


def composite(image: torch.Tensor, mask: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """image [C, H, W, 3] over `background` [C, 3] or [3] where mask [C, H, W] is 0."""
    inside, outside = composite_parts(image, mask)
    return torch.addcmul(inside, background.reshape(-1, 1, 1, 3).to(image.dtype), outside)


def ssim(a: torch.Tensor, b: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Mean SSIM of [C, H, W, 3] images (Gaussian window, as 3DGS; zero padding at the borders)."""
    return ssim_map(a, b, window, sigma).mean()


@njit(cache=True, nogil=True, error_model="numpy")
def _support_boxes(lo, hi, support, boxes) -> None:
    """Views lo..hi-1 of support [C, H, W] bool: boxes [C, 4] = (first row, last row, first column, last column) that
    hold a True pixel; last < first (-1, 0) for a view without one."""
    _, h, w = support.shape
    for c in range(lo, hi):
        y0, y1, x0, x1 = h, -1, w, -1
        for y in range(h):
            row = support[c, y]
            first = -1
            for x in range(w):
                if row[x]:
                    first = x
                    break
            if first < 0:
                continue
            last = first
            for x in range(w - 1, first, -1):
                if row[x]:
                    last = x
                    break
            y0, y1 = min(y0, y), y
            x0, x1 = min(x0, first), max(x1, last)
        boxes[c, 0], boxes[c, 1], boxes[c, 2], boxes[c, 3] = y0, y1, x0, x1


def support_windows(support: torch.Tensor, margin: int) -> tuple[torch.Tensor, int, int]:
    """One window size for all views and each view's window corner: corners [C, 2] (y0, x0), height, width.

    support [C, H, W] bool. Each view's window holds its support's bounding box grown by `margin`
    pixels (clipped to the image); all windows take the largest size so they stack into one batch.
    A view with empty support gets a window at its top-left corner. The boxes come from one pass per view that
    stops at each row's first and last True pixel (torch's any() over rows and columns was slower:
    benchmarks/results/profile.md).
    """
    c, h, w = support.shape
    boxes = np.empty((c, 4), np.int64)
    parallel_for(_support_boxes, c, support.detach().cpu().contiguous().numpy(), boxes)
    y0, y1, x0, x1 = boxes.T
    empty = y1 < 0
    y0, x0 = np.where(empty, 0, np.maximum(y0 - margin, 0)), np.where(empty, 0, np.maximum(x0 - margin, 0))
    y1, x1 = np.where(empty, 0, np.minimum(y1 + margin, h - 1)), np.where(empty, 0, np.minimum(x1 + margin, w - 1))
    wh, ww = int((y1 - y0).max()) + 1, int((x1 - x0).max()) + 1
    # A window taller or wider than a view's box slides back inside the image and still covers the box.
    corners = np.stack([np.minimum(y0, h - wh), np.minimum(x0, w - ww)], 1)
    return torch.from_numpy(corners), wh, ww


def photometric_loss(
    render: torch.Tensor,
    target: torch.Tensor,
    lambda_dssim: float = 0.2,
    support: torch.Tensor | None = None,
    window: int = 11,
    valid: torch.Tensor | None = None,
) -> torch.Tensor:
    """L_rgb = (1 - λ) L1 + λ D-SSIM, D-SSIM = 1 - SSIM (3DGS), means over every pixel of [C, H, W, 3].

    support [C, H, W] bool, optional: the pixels outside which render and target are the same colour
    (for a render composited on the target's background: where the splats or the mask reach). Outside
    it L1 is 0 and SSIM 1, so both are summed over a window around it and divided by the whole image's
    pixel count: the same value and gradient on fewer pixels (every view takes the largest view's window;
    measured: benchmarks/results/profile.md). The window grows by two SSIM radii: one
    for the windows that reach the support, one for their own windows.

    valid [C, H, W] bool, optional: the pixels each photograph has (views of mixed sizes on one canvas);
    elsewhere the render counts as equal to the target, so nothing there pulls on it.
    """
    if valid is not None:
        render = torch.where(valid[..., None], render, target)
        support = None if support is None else support & valid
    if support is None:
        l1 = (render - target).abs().mean()
        return (1 - lambda_dssim) * l1 + lambda_dssim * (1 - ssim(render, target, window))
    windows = support_windows(support, 2 * (window // 2))
    dssim_sum, l1_sum = dssim_l1_sums(render, target, window, 1.5, windows=windows)
    total = float(render.numel())
    return ((1 - lambda_dssim) * l1_sum + lambda_dssim * dssim_sum) / total


@dataclass(frozen=True)
class NeighbourGraph:
    """The k-NN pairs of L_SH as a graph Laplacian: sum_i sum_{j in N(i)} ||c_i - c_j||^2 = tr(C^T L C)
    with L = D_out + D_in - A - A^T (A_ij = 1 when j in N(i)). One sparse product per step replaces
    gathering K neighbours' coefficients, and gives the gradient 2 L C exactly."""

    laplacian: sparse.csr_matrix  # [N, N] float32, symmetric
    num_pairs: int  # pairs listed (N K when every point has K neighbours)


def neighbour_graph(neighbours: np.ndarray) -> NeighbourGraph:
    """The graph of neighbours [N, K] (indices into the same N points; -1 for none)."""
    n, k = neighbours.shape
    rows = np.repeat(np.arange(n), k)
    cols = np.asarray(neighbours, np.int64).reshape(-1)
    rows, cols = rows[cols >= 0], cols[cols >= 0]
    adj = sparse.coo_matrix((np.ones(len(cols), np.float32), (rows, cols)), shape=(n, n)).tocsr()
    degree = np.asarray(adj.sum(1)).ravel() + np.asarray(adj.sum(0)).ravel()
    lap = (sparse.diags(degree.astype(np.float32)) - adj - adj.T).tocsr()
    return NeighbourGraph(lap.astype(np.float32), len(cols))


@njit(cache=True, nogil=True, error_model="numpy")
def _csr_rows(lo, hi, indptr, indices, data, x, out) -> None:
    """out[i] = sum_jj data[jj] x[indices[jj]] over CSR row i, for rows lo..hi-1 (x [N, K], out [N, K]).

    The order and precision of scipy's own CSR product (each row's entries in turn, y += a x in x's dtype), so the
    result is the same to the bit; on two threads instead of one.
    """
    width = x.shape[1]
    for i in range(lo, hi):
        for k in range(width):
            out[i, k] = 0.0
        for jj in range(indptr[i], indptr[i + 1]):
            j = indices[jj]
            a = data[jj]
            for k in range(width):
                out[i, k] += a * x[j, k]


def csr_matmul(matrix: sparse.csr_matrix, x: np.ndarray) -> np.ndarray:
    """matrix [N, N] @ x [N, K] (same dtype), as scipy computes it, rows split over the kernel threads."""
    x = np.ascontiguousarray(x)
    out = np.empty((matrix.shape[0], x.shape[1]), x.dtype)
    parallel_for(_csr_rows, matrix.shape[0], matrix.indptr, matrix.indices, matrix.data, x, out, grain=2048)
    return out


class _Quadratic(torch.autograd.Function):
    """tr(C^T L C) / pairs for a constant symmetric L; backward reuses L C."""

    @staticmethod
    def forward(ctx, c: torch.Tensor, laplacian: sparse.csr_matrix, pairs: int) -> torch.Tensor:
        lc = torch.from_numpy(csr_matmul(laplacian, c.detach().numpy()))
        ctx.save_for_backward(lc)
        ctx.pairs = pairs
        return (c * lc).sum() / pairs

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        (lc,) = ctx.saved_tensors
        return grad * (2.0 / ctx.pairs) * lc, None, None


def neighbour_smoothness(values: torch.Tensor, graph: NeighbourGraph) -> torch.Tensor:
    """1/(N K) sum_i sum_{j in N(i)} ||v_i - v_j||^2 for values [N, ...] on the graph's N points."""
    if graph.num_pairs == 0:
        return values.sum() * 0
    return _Quadratic.apply(values.reshape(len(values), -1).float(), graph.laplacian, graph.num_pairs)


def sh_neighbour_loss(sh: torch.Tensor, graph: NeighbourGraph) -> torch.Tensor:
    """L_SH (eq. sh_smooth): the neighbour smoothness of sh [N, B, 3]."""
    return neighbour_smoothness(sh, graph)


def dropout_fraction(step: int, anneal_steps: int, p0: float = 0.5) -> float:
    """Fraction of splats dropped at Stage-II `step`: p0 cosine-annealed to 0 at `anneal_steps`, then 0."""
    if anneal_steps <= 0 or step >= anneal_steps:
        return 0.0
    return p0 * 0.5 * (1.0 + math.cos(math.pi * max(step, 0) / anneal_steps))


def dropout_active(n: int, fraction: float, generator: torch.Generator) -> torch.Tensor | None:
    """bool [n] keeping all but round(fraction * n) splats, dropped uniformly without replacement; None keeps all."""
    drop = int(round(fraction * n))
    if drop <= 0:
        return None
    active = torch.ones(n, dtype=torch.bool)
    active[torch.randperm(n, generator=generator)[:drop]] = False
    return active
