"""Differentiable tile-based Gaussian rasterization with gsplat's `classic` semantics.

CPU tensors go through the numba kernels in `_cpu_kernels`; CUDA tensors go to `gsplat.rasterization`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from reconstruction.parallel import PARTS_PER_THREAD, num_threads, parallel_for
from reconstruction.render import _cpu_kernels as kernels
from reconstruction.render.projection import Projection, project_gaussians, to_float64, to_numpy
from reconstruction.render.scratch import ScratchPool
from reconstruction.render.sh import num_sh_bases, sh_colors

# Below this many items per thread, per-splat passes run on the calling thread alone.
_GRAIN = 4096
# The CPU kernels' default tile edge. Per-slot work (listing, sorting, records, sums) outweighs the pixels a larger
# tile tests in vain: on the `cpu` preset's Stage-II batch 32-px tiles list fewer tile intersections and
# render forward+backward faster than 16-px ones, the image the same (benchmarks/results/profile.md).
CPU_TILE_SIZE = 32
# The compositing kernels' (slot, pixel) pairs and per-slot gradients, reused from call to call.
_SCRATCH = ScratchPool()


@dataclass(frozen=True)
class TileBins:
    """Depth-sorted per-tile lists of C cameras' visible splats, as slot records (see `_cpu_kernels`)."""

    tile_size: int
    tiles_x: int
    tiles_y: int
    slot_f: np.ndarray  # [n_isect, SF_COLUMNS] float64 records (mean2d, conic, opacity, ...)
    slot_i: np.ndarray  # [n_isect, SI_COLUMNS] int32 records (pixel rect within the tile)
    slot_c: np.ndarray  # [n_isect, D] float64 colour of each slot's Gaussian in its camera
    slot_offsets: np.ndarray  # [C * N + 1] int64, pair cg owns slot_at[slot_offsets[cg]:slot_offsets[cg + 1]]
    slot_at: np.ndarray  # [n_isect] int64 slots listed pair-major
    pair_offsets: np.ndarray  # [n_isect + 1] int64, room for each slot's whole pixel rect; a tile's pairs start at its first slot's
    tile_offsets: np.ndarray  # [C * tiles_y * tiles_x + 1] int64
    work: np.ndarray  # [C * tiles_y * tiles_x] tile ids grouped into per-thread bins
    work_offsets: np.ndarray  # [n_bins + 1]

    @property
    def n_isects(self) -> int:
        return int(self.slot_f.shape[0])

    @property
    def n_bins(self) -> int:
        return int(self.work_offsets.shape[0] - 1)

    @property
    def n_pairs(self) -> int:
        return int(self.slot_offsets.shape[0] - 1)

    def compositing_args(self) -> tuple:
        """Leading arguments of the compositing kernels."""
        return (
            self.slot_f,
            self.slot_c,
            self.slot_i,
            self.tile_offsets,
            self.work,
            self.work_offsets,
            self.tile_size,
            self.tiles_x,
        )

    def sum_slots(self, kernel, slot_values: np.ndarray, out: np.ndarray) -> np.ndarray:
        """out [C * N, ...] = per-pair sums of slot_values [n_isect, ...] by `kernel`."""
        parallel_for(kernel, self.n_pairs, slot_values, self.slot_offsets, self.slot_at, out, grain=_GRAIN)
        return out


def bin_gaussians(proj: Projection, opacities: Tensor, colors: Tensor, width: int, height: int) -> TileBins:
    """Lists each tile's splats sorted by depth, ties by Gaussian index, and gathers their slot records and colours.

    Args:
        proj: `project_gaussians` of C cameras with its `TileFootprints` (the tile size, each pair's pixel rect and
            tile count, and the per-chunk tile histogram); opacities: [N] float64; colors: [C, N, D] float64, or
            [1, N, D] shared by the cameras.

    Depths are compared in float64 (gsplat compares float32 depths, which merges near ties).
    """
    tile_size = proj.footprints.tile_size
    tiles_x = -(-width // tile_size)
    tiles_y = -(-height // tile_size)
    slot_offsets = np.zeros(proj.radii.shape[0] * proj.radii.shape[1] + 1, np.int64)
    np.cumsum(proj.footprints.tile_counts, out=slot_offsets[1:])
    keys, tile_offsets = _tile_keys(proj, tiles_x, tiles_y, int(slot_offsets[-1]))
    slot_f, slot_i, slot_c, slot_at, pair_offsets = _gather_slots(
        proj, opacities, colors, tiles_x, tiles_y, keys, tile_offsets, slot_offsets
    )
    work, work_offsets = kernels.balance_tiles(tile_offsets, num_threads() * PARTS_PER_THREAD)
    return TileBins(
        tile_size,
        tiles_x,
        tiles_y,
        slot_f,
        slot_i,
        slot_c,
        slot_offsets,
        slot_at,
        pair_offsets,
        tile_offsets,
        work,
        work_offsets,
    )


def _tile_keys(proj: Projection, tiles_x: int, tiles_y: int, n_isects: int) -> tuple[np.ndarray, np.ndarray]:
    """Counting sort of all slots by tile: (keys [n_isect] int64 grouped by tile, tile_offsets [C * tiles + 1] int64).

    The projection counted each chunk's slots per tile, each chunk scatters from its own cursors, then every tile's
    keys are sorted by (depth, index). Keys are unique within a tile, so the chunking does not change the result.
    """
    fp = proj.footprints
    n_cams, n = proj.radii.shape[:2]
    tiles_per_cam = tiles_x * tiles_y
    n_tiles = n_cams * tiles_per_cam
    n_chunks = fp.hist.shape[0]
    cursor = np.zeros(n_chunks * n_tiles, np.int64)
    np.cumsum(fp.hist.T.reshape(-1)[:-1], out=cursor[1:])
    tile_offsets = np.append(cursor[::n_chunks], n_isects)
    cursor = np.ascontiguousarray(cursor.reshape(n_tiles, n_chunks).T)
    # Visible depths are > near_plane > 0, whose float32 bit patterns sort like the values.
    depth_bits = to_numpy(proj.depths).reshape(-1).astype(np.float32).view(np.int32).astype(np.int64)
    keys = np.empty(n_isects, np.int64)
    parallel_for(
        kernels.scatter_tile_keys,
        n_chunks,
        n_chunks,
        fp.rects,
        fp.tile_counts,
        n,
        depth_bits,
        fp.tile_size,
        tiles_x,
        tiles_per_cam,
        cursor,
        keys,
    )
    return keys, tile_offsets


def _gather_slots(
    proj: Projection,
    opacities: Tensor,
    colors: Tensor,
    tiles_x: int,
    tiles_y: int,
    keys: np.ndarray,
    tile_offsets: np.ndarray,
    slot_offsets: np.ndarray,
) -> tuple[np.ndarray, ...]:
    """Sorts each tile's keys and gathers its slots: (slot_f, slot_i, slot_c, slot_at, pair_offsets) as in `TileBins`."""
    fp = proj.footprints
    n_cams, n = proj.radii.shape[:2]
    n_isects = keys.shape[0]
    slot_f = np.empty((n_isects, kernels.SF_COLUMNS))
    slot_i = np.empty((n_isects, kernels.SI_COLUMNS), np.int32)
    slot_c = np.empty((n_isects, colors.shape[2]))
    slot_at = np.empty(n_isects, np.int64)
    slot_areas = np.empty(n_isects, np.int64)
    parallel_for(
        kernels.tile_slots,
        n_cams * tiles_x * tiles_y,
        tile_offsets,
        keys,
        to_numpy(proj.depths).reshape(-1),
        n,
        fp.tile_size,
        tiles_x,
        tiles_x * tiles_y,
        fp.rects,
        slot_offsets,
        to_numpy(proj.means2d),
        to_numpy(proj.conics),
        to_numpy(opacities),
        fp.two_logs,
        to_numpy(colors),
        slot_f,
        slot_i,
        slot_c,
        slot_at,
        slot_areas,
    )
    pair_offsets = np.zeros(n_isects + 1, np.int64)
    np.cumsum(slot_areas, out=pair_offsets[1:])
    return slot_f, slot_i, slot_c, slot_at, pair_offsets


def _composite(bins: TileBins, backgrounds: np.ndarray, width: int, height: int, dtype: torch.dtype) -> tuple:
    """Runs the compositing kernel: (render_colors [C, H, W, D] and render_alphas [C, H, W, 1] in `dtype`,
    out_colors [C, H, W, D] and transmittance [C, H, W] float64 (set only in covered tiles: `_covered_pixels`), and the
    pairs the backward reads: slot_starts, slot_counts [n_isect], pair_px, pair_vis (lent by `_SCRATCH`))."""
    n_cams, depth = backgrounds.shape
    out_colors = np.empty((n_cams, height, width, depth))
    transmittance = np.empty((n_cams, height, width))
    render_colors = torch.empty((n_cams, height, width, depth), dtype=dtype)
    render_alphas = torch.empty((n_cams, height, width, 1), dtype=dtype)
    slot_starts = np.empty(bins.n_isects, np.int64)
    slot_counts = np.empty(bins.n_isects, np.int64)
    # The shaded (slot, pixel) pairs, kept for the backward: tile-local pixel and exp(-sigma).
    pair_px = _SCRATCH.take("pair_px", bins.pair_offsets[-1], np.uint16)
    pair_vis = _SCRATCH.take("pair_vis", bins.pair_offsets[-1], np.float64)
    parallel_for(
        kernels.rasterize_forward,
        bins.n_bins,
        *bins.compositing_args(),
        backgrounds,
        width,
        height,
        bins.pair_offsets,
        out_colors,
        transmittance,
        render_colors.numpy(),
        render_alphas.numpy()[..., 0],
        slot_starts,
        slot_counts,
        pair_px,
        pair_vis,
    )
    return render_colors, render_alphas, out_colors, transmittance, (slot_starts, slot_counts, pair_px, pair_vis)


def _covered_pixels(bins: TileBins, n_cams: int, width: int, height: int) -> np.ndarray:
    """[C, H, W] bool: the pixels of tiles that some slot covers."""
    covered = (bins.tile_offsets[1:] != bins.tile_offsets[:-1]).reshape(n_cams, bins.tiles_y, bins.tiles_x)
    pixels = np.repeat(np.repeat(covered, bins.tile_size, axis=1), bins.tile_size, axis=2)
    return pixels[:, :height, :width]


def _give_back(pairs: tuple) -> None:
    _SCRATCH.give("pair_px", pairs[2])
    _SCRATCH.give("pair_vis", pairs[3])


class _RasterizeToPixels(torch.autograd.Function):
    """Compositing of the slots listed in `bins`.

    means2d, conics, colors and opacities are the tensors the bins' slot records were gathered from, taken as inputs
    so that autograd routes their gradients; colors are [C, N, D] or [1, N, D] shared by all cameras.
    With `want_counts`, the third output is each Gaussian's shaded pixel count [C, N] (else an empty tensor).
    The pairs the forward keeps (`keep_pairs`: a graph will be differentiated) go back to the pool after the first
    backward, for the next iteration's forward; a second backward through a retained graph composites again.
    """

    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, backgrounds, bins: TileBins, width, height, dtype, keep_pairs, want_counts):
        n_cams, n = means2d.shape[:2]
        render_colors, render_alphas, out_colors, transmittance, pairs = _composite(bins, to_numpy(backgrounds), width, height, dtype)
        counts = bins.sum_slots(kernels.sum_slot_counts, pairs[1], np.empty(n_cams * n, np.int64)) if want_counts else np.empty(0, np.int64)

        ctx.save_for_backward(backgrounds)
        ctx.out_dtype = render_colors.numpy().dtype
        ctx.bins = bins
        ctx.shapes = (n_cams, n, colors.shape[0], width, height)
        ctx.out_colors = out_colors
        ctx.transmittance = transmittance
        ctx.pairs = pairs
        if not keep_pairs:
            _give_back(pairs)
            ctx.pairs = None
        counts_t = torch.from_numpy(counts).view(n_cams, n) if want_counts else torch.from_numpy(counts)
        ctx.mark_non_differentiable(counts_t)
        # An image the loss does not use (the colours of an alpha-only pass) comes back as None, not as zeros to fill.
        ctx.set_materialize_grads(False)
        return render_colors, render_alphas, counts_t

    @staticmethod
    @once_differentiable
    def backward(ctx, v_render_colors, v_render_alphas, _v_counts):
        (backgrounds,) = ctx.saved_tensors
        bins: TileBins = ctx.bins
        n_cams, n, color_cams, width, height = ctx.shapes
        pairs = ctx.pairs
        if pairs is None:
            pairs = _composite(bins, to_numpy(backgrounds), width, height, torch.float64)[4]
        ctx.pairs = None
        depth = bins.slot_c.shape[1]
        n_cols = kernels.N_GRAD_GEOMETRY + depth
        v_image = np.zeros((n_cams, height, width, depth), ctx.out_dtype) if v_render_colors is None else to_numpy(v_render_colors)
        v_alphas = np.zeros((n_cams, height, width), ctx.out_dtype) if v_render_alphas is None else to_numpy(v_render_alphas[..., 0])
        slot_grads = _SCRATCH.take("slot_grads", bins.n_isects * n_cols, np.float64).reshape(bins.n_isects, n_cols)
        kernel = kernels.rasterize_backward_rgb if depth == 3 else kernels.rasterize_backward
        parallel_for(
            kernel,
            bins.n_bins,
            *bins.compositing_args(),
            to_numpy(backgrounds),
            width,
            height,
            ctx.out_colors,
            ctx.transmittance,
            *pairs,
            v_image,
            v_alphas,
            slot_grads,
        )
        _give_back(pairs)
        v_means2d = np.empty((n_cams, n, 2))
        v_conics = np.empty((n_cams, n, 3))
        v_opacities = np.empty((n_cams, n))
        v_colors = np.empty((n_cams, n, depth))
        parallel_for(
            kernels.sum_slot_gradients,
            bins.n_pairs,
            slot_grads,
            bins.slot_offsets,
            bins.slot_at,
            v_means2d.reshape(n_cams * n, 2),
            v_conics.reshape(n_cams * n, 3),
            v_opacities.reshape(n_cams * n),
            v_colors.reshape(n_cams * n, depth),
            grain=_GRAIN,
        )
        _SCRATCH.give("slot_grads", slot_grads)
        # Summed over cameras in numpy: these arrays are small, and each torch op on them woke torch's sleeping OpenMP
        # workers at a cost above the arithmetic's (benchmarks/results/rasterizer.md).
        if color_cams == 1 and n_cams > 1:
            v_colors = v_colors.sum(0, keepdims=True)
        v_backgrounds = None
        if ctx.needs_input_grad[4]:
            transmittance = ctx.transmittance
            transmittance[~_covered_pixels(bins, n_cams, width, height)] = 1.0
            v_backgrounds = torch.einsum("chw,chwd->cd", torch.from_numpy(transmittance), torch.from_numpy(v_image).to(torch.float64))
        return (
            torch.from_numpy(v_means2d),
            torch.from_numpy(v_conics),
            torch.from_numpy(v_colors),
            torch.from_numpy(v_opacities[0] if n_cams == 1 else v_opacities.sum(0)),
            v_backgrounds,
            None,
            None,
            None,
            None,
            None,
            None,
        )


def _check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree, backgrounds, active):
    n = means.shape[0]
    n_cams = viewmats.shape[0]
    expect = {
        "means": (means, (n, 3)),
        "quats": (quats, (n, 4)),
        "scales": (scales, (n, 3)),
        "opacities": (opacities, (n,)),
        "viewmats": (viewmats, (n_cams, 4, 4)),
        "Ks": (Ks, (n_cams, 3, 3)),
    }
    for name, (tensor, shape) in expect.items():
        if tuple(tensor.shape) != shape:
            raise ValueError(f"{name} must have shape {list(shape)}, got {list(tensor.shape)}")
    if sh_degree is None:
        if colors.dim() not in (2, 3) or colors.shape[-2] != n or (colors.dim() == 3 and colors.shape[0] != n_cams):
            raise ValueError(f"colors must be [N, D] or [C, N, D] with N={n}, C={n_cams}; got {list(colors.shape)}")
    else:
        bases = num_sh_bases(sh_degree)
        if colors.dim() not in (3, 4) or colors.shape[-3] != n or colors.shape[-2] < bases or colors.shape[-1] != 3:
            raise ValueError(f"SH colors must be [N, K, 3] or [C, N, K, 3] with N={n}, K>={bases}; got {list(colors.shape)}")
    if width < 1 or height < 1:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    if backgrounds is not None and backgrounds.shape[-1] != (3 if sh_degree is not None else colors.shape[-1]):
        raise ValueError(f"backgrounds must have one value per colour channel, got {list(backgrounds.shape)}")
    if active is not None and (active.dtype != torch.bool or tuple(active.shape) != (n,)):
        raise ValueError(f"active must be a bool tensor of shape [{n}]")


def rasterize(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    *,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    sh_degree: int | None = None,
    backgrounds: Tensor | None = None,
    tile_size: int | None = None,
    active: Tensor | None = None,
    visibility_counts: bool = False,
) -> tuple[Tensor, Tensor, dict[str, Any]]:
    """Renders 3D Gaussians into C pinhole cameras, as `gsplat.rasterization` in `classic` mode (unpacked).

    Each pixel composites, front to back in depth order (ties by Gaussian index), the Gaussians whose
    alpha = min(0.999, opacity * exp(-sigma)) is >= 1/255 (pixel centres at +0.5), and stops before
    the Gaussian that would bring its transmittance T to <= 1e-4; colour = sum + T * background and
    alpha = 1 - T. See `project_gaussians` for projection and culling.

    Args:
        means: [N, 3]; quats: [N, 4] wxyz (normalised here); scales: [N, 3] linear; opacities: [N] in
            [0, 1] (post-sigmoid, as gsplat expects).
        colors: [N, D] or [C, N, D] values, or with `sh_degree` SH coefficients [N, K, 3] or
            [C, N, K, 3]; the colour is then max(SH(dir) + 0.5, 0) with dir from camera centre to mean.
            D = 0 renders the alphas alone (render_colors [C, H, W, 0]): the compositing then carries no colour
            and its per-pixel state and per-slot gradients shrink to the transmittance's.
        viewmats: [C, 4, 4] world-to-camera (OpenCV axes); Ks: [C, 3, 3] intrinsics.
        width, height: image size in pixels (any, including 1x1).
        near_plane, far_plane, eps2d: as gsplat.
        sh_degree: None for plain colours, else 0..3.
        backgrounds: optional [C, D] (or [D]) colour behind the Gaussians.
        tile_size: tile edge in pixels, at most 64 (a tile row's live pixels are one 64-bit mask); it does not
            change the image. None: `CPU_TILE_SIZE` on CPU, gsplat's 16 on a GPU.
        active: optional [N] bool; only these Gaussians are drawn and receive gradients (splat
            dropout without copying the model).
        visibility_counts: also count the pixels each Gaussian shaded (meta["visibility_counts"]); off by
            default, since training does not read them (a per-pair pass on CPU, a second rasterization on a GPU).

    Returns:
        render_colors [C, H, W, D], render_alphas [C, H, W, 1] and meta with radii [C, N, 2] int32,
        means2d [C, N, 2], conics [C, N, 3], depths [C, N], n_isects, tile_size, width, height, n_cameras,
        and with `visibility_counts` the counts [C, N] int64. On CPU, means2d and conics
        are float64 graph tensors, so `meta["means2d"].retain_grad()` gives screen-space gradients.

    Gradients flow to means, quats, scales, opacities, colors, viewmats and backgrounds (not Ks).
    """
    if tile_size is None:
        tile_size = 16 if means.is_cuda else CPU_TILE_SIZE
    width, height, tile_size = int(width), int(height), int(tile_size)
    _check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree, backgrounds, active)
    _check_options(tile_size, near_plane, eps2d)
    inputs = (means, quats, scales, opacities, colors, viewmats, Ks, width, height)
    options = dict(near_plane=near_plane, far_plane=far_plane, eps2d=eps2d, sh_degree=sh_degree, backgrounds=backgrounds)
    options |= dict(tile_size=tile_size, active=active, visibility_counts=visibility_counts)
    if means.is_cuda:
        from reconstruction.render._gsplat import rasterize_gsplat

        return rasterize_gsplat(*inputs, **options)
    return _rasterize_cpu(*inputs, **options)


def _check_options(tile_size: int, near_plane: float, eps2d: float) -> None:
    if not 1 <= tile_size <= kernels.MAX_TILE_SIZE:
        raise ValueError(f"tile_size must be between 1 and {kernels.MAX_TILE_SIZE}, got {tile_size}")
    if not near_plane > 0.0:
        raise ValueError(f"near_plane must be positive, got {near_plane}")
    if not (math.isfinite(eps2d) and eps2d >= 0.0):
        raise ValueError(f"eps2d must be a finite screen-space variance >= 0 px^2, got {eps2d}")


def _rasterize_cpu(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    *,
    near_plane: float,
    far_plane: float,
    eps2d: float,
    sh_degree: int | None,
    backgrounds: Tensor | None,
    tile_size: int,
    active: Tensor | None,
    visibility_counts: bool,
) -> tuple[Tensor, Tensor, dict[str, Any]]:
    """`rasterize` of CPU tensors (checked) by the numba kernels."""
    # One float64 copy of each input feeds every use of it (projection, SH directions), so gradients
    # from all paths are summed in float64 and rounded once, when autograd casts them back.
    dtype = colors.dtype
    means, quats, scales, opacities, colors, viewmats, Ks = to_float64(means, quats, scales, opacities, colors, viewmats, Ks)
    n_cams = viewmats.shape[0]
    proj = project_gaussians(
        means,
        quats,
        scales,
        opacities,
        viewmats,
        Ks,
        width,
        height,
        near_plane=near_plane,
        far_plane=far_plane,
        eps2d=eps2d,
        active=active,
        tile_size=tile_size,
    )
    if sh_degree is not None:
        # gsplat's convention: direction from the camera centre to the mean, DC offset 0.5, clamped at 0.
        campos = torch.linalg.inv(viewmats)[:, :3, 3]
        colors = sh_colors(sh_degree, colors, means, campos)
    if colors.dim() == 2:
        colors = colors[None]
    if backgrounds is None:
        backgrounds = torch.zeros(n_cams, colors.shape[-1], dtype=torch.float64)
    backgrounds = backgrounds.to(torch.float64).expand(n_cams, -1)

    bins = bin_gaussians(proj, opacities, colors, width, height)
    # The images come out of the kernel in the caller's dtype (float64 for any other than float32).
    out_dtype = dtype if dtype in (torch.float32, torch.float64) else torch.float64
    # Without a graph to differentiate (no_grad, or nothing requires grad) the pairs go straight back to the pool.
    keep_pairs = torch.is_grad_enabled() and any(t.requires_grad for t in (proj.means2d, proj.conics, colors, opacities, backgrounds))
    render_colors, render_alphas, counts = _RasterizeToPixels.apply(
        proj.means2d, proj.conics, colors, opacities, backgrounds, bins, width, height, out_dtype, keep_pairs, visibility_counts
    )
    meta = {
        "radii": proj.radii,
        "means2d": proj.means2d,
        "conics": proj.conics,
        "depths": proj.depths.to(dtype),
        "n_isects": bins.n_isects,
        "tile_size": tile_size,
        "width": width,
        "height": height,
        "n_cameras": n_cams,
    }
    if visibility_counts:
        meta["visibility_counts"] = counts
    return render_colors.to(dtype), render_alphas.to(dtype), meta
