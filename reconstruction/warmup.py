"""Compile every numba kernel a twin's way through the appliance asks for, once, at install time:
`python -m reconstruction.warmup`.

The kernels are cached on disk (`cache=True`, `kernel_cache`) per argument type, so a fresh install would
otherwise compile them in its first library build, reconstruction and inspection. The registration's
kernels (the silhouette index's parallel matcher and the scorer), which this warmup once left out, are among
them (measured: benchmarks/results/profile.md). Each part below runs the public functions a run calls, on a tiny scene, so that it
compiles exactly the specialisations (dtypes, layouts, read-only index arrays) a run will ask for.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import trimesh

from calibration.camera import Camera, look_at_c2w
from reconstruction.deformation import blend_anchors, farthest_point_indices
from reconstruction.inspect import line_deviation
from reconstruction.library import build_library
from reconstruction.losses import neighbour_graph, photometric_loss, sh_neighbour_loss, silhouette_losses
from reconstruction.mesh_raster import rasterize_mesh
from reconstruction.photo_consistency import consistency_loss, sample_colors
from reconstruction.registration import register
from reconstruction.render.warmup import compile_render_kernels
from reconstruction.silhouette import render_silhouette
from reconstruction.silhouette_index import GridSpec
from reconstruction.ssim import dssim_l1_sums, ssim_map


def compile_training_kernels() -> None:
    """The rasterizer in every mode (`render.warmup`), SSIM (the loss's SSIM + L1 sums in float32 with gradients, over
    whole images and over windows around the support; the metric in float64), the silhouette losses, the
    photo-consistency term, the neighbour-smoothness product, the field's anchors and their blend (float32, with
    gradients)."""
    compile_render_kernels()
    n, w, h = 64, 32, 24
    gen = torch.Generator().manual_seed(0)
    means = torch.randn(n, 3, generator=gen) * 0.1 + torch.tensor([0.0, 0.0, 2.0])
    viewmats = torch.eye(4).repeat(2, 1, 1)
    ks = torch.tensor([[30.0, 0, w / 2], [0, 30.0, h / 2], [0, 0, 1]]).repeat(2, 1, 1)
    image = torch.rand(2, h, w, 3, generator=gen).requires_grad_(True)
    ssim_map(image, torch.rand(2, h, w, 3, generator=gen)).sum().backward()
    ssim_map(image.detach().double(), image.detach().double())  # the evaluation metric's float64 map
    sum(dssim_l1_sums(image, torch.rand(2, h, w, 3, generator=gen))).backward()
    support = torch.zeros(2, h, w, dtype=torch.bool)
    support[:, 8:16, 10:20] = True
    photometric_loss(image, torch.rand(2, h, w, 3, generator=gen), support=support).backward()
    alpha = torch.rand(2, h, w, 1, generator=gen).requires_grad_(True)
    sum(silhouette_losses(alpha, torch.rand(2, h, w, generator=gen), torch.ones(2, h, w, dtype=torch.bool))).backward()
    points = means.clone().requires_grad_(True)
    colors = sample_colors(image.detach(), points, viewmats.clone().requires_grad_(True), ks)
    consistency_loss(colors, torch.ones(2, n)).backward()
    ring = neighbour_graph((np.arange(n)[:, None] + np.array([1, 2])) % n)
    sh_neighbour_loss(torch.rand(n, 9, 3, generator=gen).requires_grad_(True), ring).backward()
    farthest_point_indices(means.detach().double().numpy(), 8)
    anchors = torch.rand(8, 3, generator=gen).requires_grad_(True)
    blend_anchors(anchors, torch.randint(0, 8, (n, 4), generator=gen), torch.full((n, 4), 0.25)).sum().backward()


def _part() -> trimesh.Trimesh:
    """An L-shaped part about 10 cm across: no symmetry for the registration to report."""
    bar = trimesh.creation.box([0.10, 0.03, 0.02])
    post = trimesh.creation.box([0.02, 0.06, 0.02], transform=trimesh.transformations.translation_matrix([0.04, 0.045, 0.0]))
    return trimesh.util.concatenate([bar, post])


def compile_registration_kernels(work: Path) -> None:
    """A one-part library built at `work` (the silhouette renderer and the index's bit counts) and a registration
    against it (the index's matcher, the silhouette scorer), then the mesh renderers export and inspection use."""
    part = _part()
    (work / "meshes").mkdir()
    part.export(work / "meshes" / "part.stl")
    library = build_library(
        work / "meshes", work / "library", grid=GridSpec(n_dirs=60), workers=1, progress=False, log=lambda _message: None
    )
    size = (80, 60)
    cameras = [
        Camera.from_fov(np.radians(50.0), *size, look_at_c2w(eye, np.zeros(3)))
        for eye in ([0.3, 0.0, 0.1], [0.0, 0.3, 0.12], [-0.25, -0.15, 0.1])
    ]
    masks = np.stack([render_silhouette(part.vertices, part.faces, c.K, c.viewmat, *size) for c in cameras])
    register(masks, cameras, library)
    rasterize_mesh(np.asarray(part.vertices), np.asarray(part.faces), cameras[0])
    normals = np.asarray(part.vertex_normals)
    line_deviation(np.asarray(part.vertices), normals, np.asarray(part.vertices), np.asarray(part.faces), 0.01)


def compile_kernels() -> float:
    """Compiles (or loads) every kernel; returns the seconds it took."""
    t0 = time.perf_counter()
    compile_training_kernels()
    with tempfile.TemporaryDirectory(prefix="cadsplat-warmup-") as work:
        compile_registration_kernels(Path(work))
    return time.perf_counter() - t0


def main() -> None:
    print(f"training, registration and inspection kernels compiled and cached in {compile_kernels():.1f} s")


if __name__ == "__main__":
    main()
