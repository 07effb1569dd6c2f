"""Differentiable Gaussian rasterization: numba kernels on the CPU, gsplat on CUDA."""

from reconstruction.render.projection import Projection, project_gaussians
from reconstruction.render.rasterization import rasterize
from reconstruction.render.sh import eval_sh, num_sh_bases

__all__ = ["Projection", "eval_sh", "num_sh_bases", "project_gaussians", "rasterize"]
