"""The speed anchor: one forward + backward of a tiled pure-PyTorch rasterizer, 20k splats at 256².

Every speed figure the appliance states is a ratio to this step measured in the same run, so it
moves with the machine as the engine does (a twin "at 27x the anchor" means 27 anchor steps of wall
time). The workload is fixed: torch is pinned, this code is frozen, and the splats lie on the YCB
banana scan shipped beside this file (geometry only; CC BY 4.0, Calli et al.), so a fresh clone and
the benchmarks time the same thing. `python -m reconstruction.render.anchor` prints one reading.

The rasterizer has gsplat's classic semantics (pinhole projection with the 0.3 px low-pass, 16-px
tiles sorted by depth, 1/255 alpha and 1e-4 transmittance cut-offs) written as plain torch ops.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

ANCHOR_MESH = Path(__file__).with_name("anchor_011_banana.ply")
SPLATS = 20_000
SIZE = 256
TARGET_COVERAGE = 0.30


def quats_from_normals(normals: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """wxyz quaternions [N, 4] rotating +z onto each normal [N, 3], with a random spin about the normal."""
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, normals)
    s = np.linalg.norm(axis, axis=1, keepdims=True)
    half = np.arctan2(s[:, 0], normals @ z) / 2.0
    axis = np.where(s > 1e-9, axis / np.maximum(s, 1e-12), np.array([1.0, 0.0, 0.0]))
    align = np.concatenate([np.cos(half)[:, None], np.sin(half)[:, None] * axis], axis=1)
    spin = rng.uniform(0.0, np.pi, len(normals))
    q2 = np.stack([np.cos(spin), np.zeros_like(spin), np.zeros_like(spin), np.sin(spin)], axis=1)
    w1, v1 = align[:, :1], align[:, 1:]
    w2, v2 = q2[:, :1], q2[:, 1:]
    return np.concatenate([w1 * w2 - (v1 * v2).sum(1, keepdims=True), w1 * v2 + w2 * v1 + np.cross(v1, v2)], axis=1)


def surface_gaussians(mesh, n: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """n Gaussians on a trimesh surface: tangent sigma ~ half the mean sample spacing, normal sigma a tenth.

    Returns means [n, 3], quats [n, 4] (wxyz), scales [n, 3], opacities [n], colors [n, 3], float32.
    """
    import trimesh

    rng = np.random.default_rng(seed)
    points, faces = trimesh.sample.sample_surface(mesh, n, seed=seed)
    spacing = math.sqrt(mesh.area / n)
    tangent = 0.5 * spacing * np.exp(0.3 * rng.standard_normal((n, 2)))
    scales = np.concatenate([tangent, 0.1 * tangent[:, :1]], axis=1)
    return {
        "means": torch.tensor(points, dtype=torch.float32),
        "quats": torch.tensor(quats_from_normals(mesh.face_normals[faces], rng), dtype=torch.float32),
        "scales": torch.tensor(scales, dtype=torch.float32),
        "opacities": torch.tensor(rng.uniform(0.3, 1.0, n), dtype=torch.float32),
        "colors": torch.tensor(rng.uniform(0.0, 1.0, (n, 3)), dtype=torch.float32),
    }


def diagonal_camera(mesh, size: int, focal: float) -> tuple[torch.Tensor, torch.Tensor]:
    """viewmat [1, 4, 4] and K [1, 3, 3] of a square camera looking at the mesh centre from a diagonal, 4 bounding radii away."""
    centre = mesh.bounds.mean(axis=0)
    radius = float(np.linalg.norm(mesh.extents)) / 2.0
    eye = centre + 4.0 * radius * np.array([0.5, -0.6, 0.62]) / np.linalg.norm([0.5, -0.6, 0.62])
    fwd = (centre - eye) / np.linalg.norm(centre - eye)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    R = np.stack([right, np.cross(fwd, right), fwd])
    viewmat = np.eye(4)
    viewmat[:3, :3], viewmat[:3, 3] = R, -R @ eye
    K = np.array([[focal, 0.0, size / 2], [0.0, focal, size / 2], [0.0, 0.0, 1.0]])
    return torch.tensor(viewmat, dtype=torch.float32)[None], torch.tensor(K, dtype=torch.float32)[None]


def torch_project(means, quats, scales, opacities, viewmat, K, width, height, eps2d=0.3, near=0.01):
    """gsplat's pinhole projection in torch: (means2d [N, 2], conics [N, 3], depths [N], radii [N, 2], visible [N])."""
    q = torch.nn.functional.normalize(quats, dim=-1)
    w, x, y, z = q.unbind(-1)
    R = torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(-1, 3, 3)
    M = R * scales[:, None, :]
    Rc, t = viewmat[:3, :3], viewmat[:3, 3]
    mc = means @ Rc.T + t
    cov_c = Rc @ (M @ M.transpose(1, 2)) @ Rc.T
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    tz = mc[:, 2].clamp_min(near)
    lim_x, lim_y = 0.3 * 0.5 * width / fx, 0.3 * 0.5 * height / fy
    tx = tz * torch.clamp(mc[:, 0] / tz, -(cx / fx + lim_x), (width - cx) / fx + lim_x)
    ty = tz * torch.clamp(mc[:, 1] / tz, -(cy / fy + lim_y), (height - cy) / fy + lim_y)
    zero = torch.zeros_like(tz)
    J = torch.stack([fx / tz, zero, -fx * tx / tz**2, zero, fy / tz, -fy * ty / tz**2], -1).reshape(-1, 2, 3)
    cov2 = J @ cov_c @ J.transpose(1, 2) + eps2d * torch.eye(2)
    det = cov2[:, 0, 0] * cov2[:, 1, 1] - cov2[:, 0, 1] ** 2
    conics = torch.stack([cov2[:, 1, 1], -cov2[:, 0, 1], cov2[:, 0, 0]], -1) / det[:, None]
    means2d = torch.stack([fx * mc[:, 0] / tz + cx, fy * mc[:, 1] / tz + cy], -1)
    with torch.no_grad():
        extent = torch.sqrt(2.0 * torch.log(255.0 * opacities.clamp_min(1.0 / 255.0)))
        radii = torch.ceil(extent[:, None] * torch.stack([cov2[:, 0, 0], cov2[:, 1, 1]], -1).sqrt())
        visible = (mc[:, 2] > near) & (det > 0) & (opacities >= 1.0 / 255.0)
        visible &= (means2d + radii > 0).all(-1) & (means2d[:, 0] - radii[:, 0] < width)
        visible &= means2d[:, 1] - radii[:, 1] < height
    return means2d, conics, mc[:, 2], radii, visible


@torch.no_grad()
def torch_bin(means2d, radii, depths, visible, width, height, tile_size):
    """Tile lists as in gsplat's isect_tiles: (gaussian ids sorted by (tile, depth), tile offsets [T + 1])."""
    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    lo = torch.floor((means2d - radii) / tile_size).long()
    hi = torch.ceil((means2d + radii) / tile_size).long()
    lo[:, 0].clamp_(0, tiles_x), hi[:, 0].clamp_(0, tiles_x)
    lo[:, 1].clamp_(0, tiles_y), hi[:, 1].clamp_(0, tiles_y)
    span = (hi - lo).clamp_min(0)
    counts = span[:, 0] * span[:, 1] * visible
    ids = torch.repeat_interleave(torch.arange(len(counts)), counts)
    local = torch.arange(len(ids)) - torch.repeat_interleave(torch.cumsum(counts, 0) - counts, counts)
    tx = lo[ids, 0] + local % span[ids, 0]
    ty = lo[ids, 1] + local // span[ids, 0]
    tile = ty * tiles_x + tx
    depth_rank = torch.argsort(torch.argsort(depths, stable=True))
    order = torch.argsort(tile * len(depths) + depth_rank[ids])
    offsets = torch.zeros(tiles_x * tiles_y + 1, dtype=torch.long)
    offsets[1:] = torch.cumsum(torch.bincount(tile, minlength=tiles_x * tiles_y), 0)
    return ids[order], offsets


def torch_tiled_rasterize(means, quats, scales, opacities, colors, viewmat, K, width, height, tile_size=16):
    """Tiled pure-PyTorch rasterizer, one camera: rgb [H, W, 3] and alpha [H, W]."""
    means2d, conics, depths, radii, visible = torch_project(means, quats, scales, opacities, viewmat, K, width, height)
    ids, offsets = torch_bin(means2d, radii, depths, visible, width, height, tile_size)
    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    ys, xs = torch.meshgrid(torch.arange(tile_size) + 0.5, torch.arange(tile_size) + 0.5, indexing="ij")
    local_pix = torch.stack([xs, ys], -1).reshape(-1, 2)
    tiles_rgb, tiles_t = [], []
    for t in range(tiles_x * tiles_y):
        g = ids[offsets[t] : offsets[t + 1]]
        if len(g) == 0:
            tiles_rgb.append(torch.zeros(tile_size * tile_size, 3, dtype=means2d.dtype))
            tiles_t.append(torch.ones(tile_size * tile_size, dtype=means2d.dtype))
            continue
        origin = torch.tensor([(t % tiles_x) * tile_size, (t // tiles_x) * tile_size], dtype=torch.float32)
        d = (local_pix + origin)[:, None, :] - means2d[g][None]
        a, b, c = conics[g].unbind(-1)
        sigma = 0.5 * (a * d[..., 0] ** 2 + c * d[..., 1] ** 2) + b * d[..., 0] * d[..., 1]
        alpha = torch.clamp(opacities[g] * torch.exp(-sigma), max=0.999)
        alpha = torch.where((sigma >= 0) & (alpha >= 1.0 / 255.0), alpha, torch.zeros_like(alpha))
        t_after = torch.cumprod(1.0 - alpha, dim=1)
        contributes = t_after > 1e-4
        t_before = torch.cat([torch.ones_like(t_after[:, :1]), t_after[:, :-1]], 1)
        weights = torch.where(contributes, alpha * t_before, torch.zeros_like(alpha))
        tiles_rgb.append(weights @ colors[g])
        tiles_t.append(torch.where(contributes, 1.0 - alpha, torch.ones_like(alpha)).prod(1))
    rgb = torch.stack(tiles_rgb).reshape(tiles_y, tiles_x, tile_size, tile_size, 3)
    trans = torch.stack(tiles_t).reshape(tiles_y, tiles_x, tile_size, tile_size)
    rgb = rgb.permute(0, 2, 1, 3, 4).reshape(tiles_y * tile_size, tiles_x * tile_size, 3)[:height, :width]
    trans = trans.permute(0, 2, 1, 3).reshape(tiles_y * tile_size, tiles_x * tile_size)[:height, :width]
    return rgb, 1.0 - trans


def fit_focal(mesh, size: int, coverage: float = TARGET_COVERAGE) -> float:
    """The focal length at which alpha > 0.5 covers about `coverage` of a size² image of 20k splats on `mesh`."""
    from reconstruction.render import rasterize

    g = surface_gaussians(mesh, SPLATS, seed=1)
    focal = float(size)
    for _ in range(4):
        viewmat, K = diagonal_camera(mesh, size, focal)
        _, alphas, _ = rasterize(*g.values(), viewmat, K, size, size)
        focal *= math.sqrt(coverage / max(float((alphas > 0.5).float().mean()), 1e-3))
    return focal


def anchor_step_in_process(iters: int = 3) -> float:
    """Median wall ms of `iters` anchor steps (after one untimed) in this process, under its OpenMP settings."""
    import trimesh

    mesh = trimesh.load(ANCHOR_MESH, process=False)
    g = surface_gaussians(mesh, SPLATS)
    viewmat, K = diagonal_camera(mesh, SIZE, fit_focal(mesh, SIZE))
    params = [g[k].clone().requires_grad_(True) for k in ("means", "quats", "scales", "opacities", "colors")]
    target = torch.rand(SIZE, SIZE, 3, generator=torch.Generator().manual_seed(0))

    def step():
        for p in params:
            p.grad = None
        rgb, _ = torch_tiled_rasterize(*params, viewmat[0], K[0], SIZE, SIZE)
        ((rgb - target) ** 2).sum().backward()

    step()
    walls = []
    for _ in range(iters):
        t = time.perf_counter()
        step()
        walls.append(1000.0 * (time.perf_counter() - t))
    return float(np.median(walls))


def anchor_ms(iters: int = 3) -> float:
    """Median wall ms of one anchor step on this machine now, measured in a child process.

    The child's OpenMP workers sleep at once (OMP_WAIT_POLICY=PASSIVE): made of thousands of small torch
    ops, the step reads mostly how fast a sleeping core wakes, so the engine's own spin setting
    (`reconstruction.parallel.configure_openmp`) would change the yardstick if it ran in the caller.
    """
    env = {k: v for k, v in os.environ.items() if k != "GOMP_SPINCOUNT"}
    env["OMP_WAIT_POLICY"] = "PASSIVE"
    out = subprocess.run(
        [sys.executable, "-m", "reconstruction.render.anchor", "--iters", str(iters)], check=True, capture_output=True, text=True, env=env
    ).stdout
    return float(json.loads(out.strip().splitlines()[-1])["anchor_ms"])


def ratio_line(wall_s: float, anchor: float) -> str:
    """'38.1 s, 27x the anchor (1.41 s a step)': a wall time against the anchor step read in the same run."""
    return f"{wall_s:.1f} s, {1000.0 * wall_s / anchor:.0f}x the anchor ({anchor / 1000.0:.2f} s a step)"


def main() -> None:
    import argparse

    ap = argparse.ArgumentParser(
        description="Time the speed anchor: one forward+backward of the tiled pure-PyTorch rasterizer, 20k splats at 256²."
    )
    ap.add_argument("--iters", type=int, default=3)
    args = ap.parse_args()
    torch.set_num_threads(os.cpu_count() or 1)
    print(json.dumps({"anchor_ms": anchor_step_in_process(args.iters)}))


if __name__ == "__main__":
    main()
