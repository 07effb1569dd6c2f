"""Deformation field (paper 3.5): Δμ = D(γ(μ)), an MLP on sinusoidal features of canonical positions.

Positions are normalised by the object's bounding sphere before encoding, so the same bands fit a
part in millimetres and one in metres, and the head's output is scaled back by the radius (the
learning rate then means the same thing for every object). The head is zero-initialised: the field
starts as the identity.

On a CPU the MLP need not run at every splat: with `anchors`, it runs at M anchor points (farthest-
point subsample of the splats) and each splat takes a fixed inverse-distance blend of its k nearest
anchors' offsets. The field stays smooth (it is a smooth MLP blended with smooth weights) and its
cost drops from N to M evaluations.

On a CPU with native bfloat16 dot products (AVX512-BF16, AMX) the hidden layers' matrix products run in
bfloat16 with float32 accumulation (torch autocast; weights, encoding and the linear head stay float32): about
half the time, at a small relative error in the offsets (benchmarks/results/profile.md). Training and
export evaluate the field the same way (`_mlp_at`), so the mesh moves as the splats did.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import nn


@dataclass(frozen=True)
class FieldConfig:
    depth: int = 8
    width: int = 256
    bands: int = 10
    num_anchors: int | None = None  # None: evaluate at every splat (the paper)
    anchor_k: int = 4
    # Remove the field's best-fit similarity (translation, infinitesimal rotation, uniform scale) at
    # its evaluation points, so the field cannot mimic the global Sim(3) the pose correction owns.
    project_similarity: bool = False
    # With `project_similarity`, keep the uniform scaling in the field (remove only the rigid motion):
    # on a metric rig the pose's scale is fixed by the calibration, and a part larger than its CAD
    # model is a deformation to measure, not a pose.
    projection_keeps_scale: bool = False


def _native_bf16() -> bool:
    """True when this CPU multiplies bfloat16 natively; elsewhere bfloat16 matmuls are emulated and slower."""
    probe = getattr(torch.cpu, "_is_avx512_bf16_supported", None)
    return bool(probe is not None and probe())


CPU_BF16_MATMUL = _native_bf16()


def positional_encoding(x: torch.Tensor, bands: int) -> torch.Tensor:
    """γ(x) for x [N, 3] in about [-1, 1] -> [N, 3 + 6 * bands]: x, sin(2^l π x), cos(2^l π x)."""
    freqs = (2.0 ** torch.arange(bands, dtype=x.dtype, device=x.device)) * math.pi
    xf = x[:, None, :] * freqs[:, None]  # [N, L, 3]
    return torch.cat([x, torch.sin(xf).flatten(1), torch.cos(xf).flatten(1)], 1)


class DeformationMLP(nn.Module):
    """depth x width ReLU MLP; the encoding is concatenated again after layer depth // 2; linear head -> 3."""

    def __init__(self, in_dim: int, depth: int, width: int):
        super().__init__()
        if depth < 1 or width < 1:
            raise ValueError(f"deformation MLP needs depth and width >= 1, got {depth}x{width}")
        self.skip = depth // 2
        layers = []
        for i in range(depth):
            d_in = in_dim if i == 0 else width
            if i == self.skip and i > 0:
                d_in = width + in_dim
            layers.append(nn.Linear(d_in, width))
        self.layers = nn.ModuleList(layers)
        self.head = nn.Linear(width, 3)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def features(self, enc: torch.Tensor) -> torch.Tensor:
        """The last hidden layer [N, width] for the encoding enc [N, in_dim]."""
        h = enc
        for i, layer in enumerate(self.layers):
            if i == self.skip and i > 0:
                h = torch.cat([h, enc], 1)
            h = torch.relu(layer(h))
        return h

    def forward(self, enc: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(enc))


def similarity_basis(points: torch.Tensor, with_scale: bool = True) -> torch.Tensor:
    """Offsets [P * 3, 7] of points [P, 3] (about their centre, in about [-1, 1]) under the 7 infinitesimal
    similarities: 3 translations, 3 rotations (ω × x), 1 uniform scaling (x); [P * 3, 6] (rigid) without scale."""
    p = len(points)
    eye = torch.eye(3, dtype=points.dtype).expand(p, 3, 3)  # [P, 3 (dim), 3 (generator)]
    rot = torch.cross(torch.eye(3, dtype=points.dtype)[None].expand(p, 3, 3), points[:, None, :].expand(p, 3, 3), dim=-1)
    cols = torch.cat([eye, rot.transpose(1, 2), *([points[:, :, None]] if with_scale else [])], 2)  # [P, 3, 7 or 6]
    return cols.reshape(p * 3, -1)


def normal_similarity_basis(
    points: np.ndarray, normals: np.ndarray, center: np.ndarray, radius: float, with_scale: bool = True
) -> np.ndarray:
    """[P, 7] (or [P, 6] without scale) normal components n . b of the infinitesimal similarities at points
    [P, 3] with unit normals [P, 3]: the moves along the normals (in units of `radius`) that a pose makes."""
    x = (np.asarray(points, np.float64) - np.asarray(center, np.float64)) / float(radius)
    basis = similarity_basis(torch.from_numpy(x), with_scale=with_scale).numpy().reshape(len(x), 3, -1)
    return np.einsum("pd,pdk->pk", np.asarray(normals, np.float64), basis)


def remove_similarity(offsets: torch.Tensor, basis: torch.Tensor, pinv: torch.Tensor) -> torch.Tensor:
    """offsets [P, 3] minus their least-squares fit by `basis` [P * 3, 7] (pinv = its pseudo-inverse [7, P * 3])."""
    flat = offsets.reshape(-1)
    return (flat - basis @ (pinv @ flat)).reshape(offsets.shape)


@numba.njit(cache=True, nogil=True)
def _farthest_points(pts: np.ndarray, idx: np.ndarray) -> None:
    """Fills idx[1:] greedily, each the point farthest from those before it (ties: the lowest index)."""
    n = pts.shape[0]
    d = np.empty(n)
    for j in range(n):
        dx, dy, dz = pts[j, 0] - pts[idx[0], 0], pts[j, 1] - pts[idx[0], 1], pts[j, 2] - pts[idx[0], 2]
        d[j] = dx * dx + dy * dy + dz * dz
    for i in range(1, idx.shape[0]):
        best = 0
        for j in range(1, n):
            if d[j] > d[best]:
                best = j
        idx[i] = best
        for j in range(n):
            dx, dy, dz = pts[j, 0] - pts[best, 0], pts[j, 1] - pts[best, 1], pts[j, 2] - pts[best, 2]
            d[j] = min(d[j], dx * dx + dy * dy + dz * dz)


def farthest_point_indices(points: np.ndarray, m: int, seed: int = 0) -> np.ndarray:
    """Indices [m] of a farthest-point subsample of points [N, 3] (m clipped to N)."""
    pts = np.ascontiguousarray(points, np.float64)
    m = min(m, len(pts))
    idx = np.empty(m, np.int64)
    if m == 0:
        return idx
    idx[0] = np.random.default_rng(seed).integers(len(pts))
    _farthest_points(pts, idx)
    return idx


def idw_weights(points: np.ndarray, anchors: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """k nearest anchors [N, k] of each point and inverse-square-distance weights [N, k] summing to 1.

    A point on an anchor takes that anchor's value exactly (the weight formula is regularised by a
    floor of 1e-6 of the mean anchor spacing).
    """
    k = min(k, len(anchors))
    tree = cKDTree(np.asarray(anchors, np.float64))
    dist, idx = tree.query(np.asarray(points, np.float64), k=k, workers=-1)
    dist, idx = dist.reshape(len(points), k), idx.reshape(len(points), k)
    spacing = float(np.mean(tree.query(anchors, k=min(2, len(anchors)))[0][:, -1])) if len(anchors) > 1 else 1.0
    w = 1.0 / np.maximum(dist, 1e-6 * max(spacing, 1e-12)) ** 2
    return idx.astype(np.int64), (w / w.sum(1, keepdims=True)).astype(np.float32)


@numba.njit(cache=True, nogil=True)
def _blend_rows(idx: np.ndarray, w: np.ndarray, rows: np.ndarray, out: np.ndarray) -> None:
    """out[n] = sum_j w[n, j] rows[idx[n, j]] for idx, w [N, k], rows [M, D], out [N, D]."""
    for n in range(idx.shape[0]):
        for c in range(rows.shape[1]):
            total = 0.0
            for j in range(idx.shape[1]):
                total += w[n, j] * rows[idx[n, j], c]
            out[n, c] = total


@numba.njit(cache=True, nogil=True)
def _scatter_rows(idx: np.ndarray, w: np.ndarray, grad: np.ndarray, out: np.ndarray) -> None:
    """The transpose of `_blend_rows`: out [M, D] = sum over (n, j) with idx[n, j] = m of w[n, j] grad[n], in order."""
    out[:] = 0.0
    for n in range(idx.shape[0]):
        for j in range(idx.shape[1]):
            m = idx[n, j]
            for c in range(grad.shape[1]):
                out[m, c] += w[n, j] * grad[n, c]


class _AnchorBlend(torch.autograd.Function):
    """Each splat's fixed inverse-distance blend of its k anchors' offsets. Autograd's own backward of the
    gather `d[idx]` is an accumulating index_put; this scatter of the same sums is an order of magnitude cheaper."""

    @staticmethod
    def forward(ctx, rows: torch.Tensor, idx: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        out = np.empty((idx.shape[0], rows.shape[1]), np.float32)
        _blend_rows(idx.numpy(), w.numpy(), rows.detach().contiguous().numpy(), out)
        ctx.save_for_backward(idx, w)
        ctx.num_rows = rows.shape[0]
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        idx, w = ctx.saved_tensors
        out = np.empty((ctx.num_rows, grad.shape[1]), np.float32)
        _scatter_rows(idx.numpy(), w.numpy(), grad.contiguous().numpy(), out)
        return torch.from_numpy(out), None, None


def blend_anchors(rows: torch.Tensor, idx: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """[N, D] = sum_j w[:, j, None] * rows[idx[:, j]] for rows [M, D], idx [N, k] int64, w [N, k] (float32 on CPU through
    numba, else torch)."""
    if rows.device.type == "cpu" and rows.dtype == torch.float32 and w.dtype == torch.float32:
        return _AnchorBlend.apply(rows, idx, w)
    return torch.einsum("nk,nkd->nd", w, rows[idx])


class DeformationField(nn.Module):
    """Offsets Δμ [N, 3] for the fixed canonical means [N, 3] it was built on (object frame, metres)."""

    def __init__(
        self,
        means_canonical: np.ndarray,
        config: FieldConfig = FieldConfig(),
        *,
        seed: int = 0,
        center: np.ndarray | None = None,
        radius: float | None = None,
    ):
        super().__init__()
        self.config = config
        pts = np.asarray(means_canonical, np.float64)
        lo, hi = pts.min(0), pts.max(0)
        c = (lo + hi) / 2 if center is None else np.asarray(center, np.float64)
        r = float(np.linalg.norm(pts - c, axis=1).max()) if radius is None else float(radius)
        r = max(r, 1e-9)
        self.register_buffer("center", torch.tensor(c, dtype=torch.float32))
        self.register_buffer("radius", torch.tensor(r, dtype=torch.float32))
        self.mlp = DeformationMLP(3 + 6 * config.bands, config.depth, config.width)
        # Hidden layers in bfloat16 (CPU only): decided once, so that a field evaluates the same way all its life.
        self.bf16 = CPU_BF16_MATMUL
        if config.num_anchors is not None and config.num_anchors < len(pts):
            anchors = pts[farthest_point_indices(pts, config.num_anchors, seed)]
            idx, w = idw_weights(pts, anchors, config.anchor_k)
            self.register_buffer("anchors", torch.tensor(anchors, dtype=torch.float32))
            self.register_buffer("anchor_idx", torch.from_numpy(idx))
            self.register_buffer("anchor_w", torch.from_numpy(w))
            self.register_buffer("points", torch.zeros(0, 3))
        else:
            self.register_buffer("anchors", None)
            self.register_buffer("points", torch.tensor(pts, dtype=torch.float32))
        self._set_projection()

    def _set_projection(self) -> None:
        """Similarity basis and pseudo-inverse at the evaluation points (anchors or splats), or none."""
        if not self.config.project_similarity:
            self.sim_basis, self.sim_pinv = None, None
            return
        at = self.anchors if self.anchors is not None else self.points
        x = (at.double() - self.center.double()) / self.radius.double()
        basis = similarity_basis(x, with_scale=not self.config.projection_keeps_scale)
        self.sim_basis, self.sim_pinv = basis.float(), torch.linalg.pinv(basis).float()

    @property
    def num_evaluations(self) -> int:
        """MLP evaluations per forward pass."""
        return len(self.anchors) if self.anchors is not None else len(self.points)

    def _mlp_at(self, x: torch.Tensor) -> torch.Tensor:
        xn = (x - self.center) / self.radius
        enc = positional_encoding(xn, self.config.bands)
        if not (self.bf16 and x.device.type == "cpu"):
            return self.mlp(enc) * self.radius
        with torch.autocast("cpu", dtype=torch.bfloat16):
            # The encoding in bfloat16 once (each layer would cast it anyway), so the skip's concatenation stays in it.
            h = self.mlp.features(enc.to(torch.bfloat16))
        return self.mlp.head(h.to(enc.dtype)) * self.radius

    def forward(self) -> torch.Tensor:
        """Δμ [N, 3] at the canonical means."""
        if self.anchors is None:
            return self._project(self._mlp_at(self.points))
        d = self._project(self._mlp_at(self.anchors))
        return blend_anchors(d, self.anchor_idx, self.anchor_w)

    def _project(self, d: torch.Tensor) -> torch.Tensor:
        return d if self.sim_basis is None else remove_similarity(d, self.sim_basis, self.sim_pinv)

    @torch.no_grad()
    def offsets_at(self, points: np.ndarray) -> np.ndarray:
        """Δ [P, 3] at arbitrary canonical points (e.g. CAD vertices), the same field the splats see."""
        pts = np.asarray(points, np.float64)
        if self.anchors is None:
            # Without anchors the field lives at the splats: other points take an IDW blend of the
            # splats' (projected) offsets, so the mesh moves exactly as the splats around it do.
            if self.sim_basis is None:
                return self._mlp_at(torch.tensor(pts, dtype=torch.float32)).numpy().astype(np.float64)
            anchors, d = self.points.numpy(), self.forward().numpy()
        else:
            anchors, d = self.anchors.numpy(), self._project(self._mlp_at(self.anchors)).numpy()
        idx, w = idw_weights(pts, anchors, self.config.anchor_k)
        return np.einsum("nk,nkd->nd", w, d[idx]).astype(np.float64)
