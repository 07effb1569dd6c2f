import numpy as np
import torch
import trimesh

from reconstruction.render import rasterize
from reconstruction.render.anchor import ANCHOR_MESH, anchor_ms, diagonal_camera, ratio_line, surface_gaussians, torch_tiled_rasterize


def test_the_anchor_renders_what_the_engine_renders():
    """The yardstick is a real rasterizer of the same model, not an arbitrary workload."""
    mesh = trimesh.load(ANCHOR_MESH, process=False)
    g = surface_gaussians(mesh, 500)
    viewmat, K = diagonal_camera(mesh, 48, 120.0)
    with torch.no_grad():
        rgb, alpha = torch_tiled_rasterize(*g.values(), viewmat[0], K[0], 48, 48)
    ours_rgb, ours_alpha, _ = rasterize(*g.values(), viewmat, K, 48, 48)
    assert float(alpha.max()) > 0.5
    np.testing.assert_allclose(alpha.numpy(), ours_alpha[0].numpy().squeeze(), atol=1e-4)
    np.testing.assert_allclose(rgb.numpy(), ours_rgb[0].numpy(), atol=1e-4)


def test_the_anchor_is_read_in_a_child_process_and_stated_as_a_ratio():
    ms = anchor_ms(iters=1)
    assert ms > 0
    assert ratio_line(60.0, 2000.0) == "60.0 s, 30x the anchor (2.00 s a step)"
