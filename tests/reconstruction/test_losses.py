"""Losses: schedule values, SH neighbour loss, mask L1, composite, SSIM sanity."""

from __future__ import annotations

import math

import numpy as np
import torch

from reconstruction.losses import (
    composite,
    dropout_active,
    dropout_fraction,
    fill_loss,
    mask_l1,
    photometric_loss,
    sh_neighbour_loss,
    ssim,
)


def test_dropout_schedule_values():
    # Paper: 0.5 at the start of Stage II, cosine to 0 over 20k iterations, 0 for the last 4k.
    assert dropout_fraction(0, 20_000) == 0.5
    assert math.isclose(dropout_fraction(10_000, 20_000), 0.25)
    assert math.isclose(dropout_fraction(5_000, 20_000), 0.25 * (1 + math.cos(math.pi / 4)))
    assert dropout_fraction(20_000, 20_000) == 0.0
    assert dropout_fraction(23_999, 20_000) == 0.0
    assert dropout_fraction(0, 0) == 0.0
    vals = [dropout_fraction(s, 100) for s in range(101)]
    assert all(a >= b for a, b in zip(vals, vals[1:]))


def test_dropout_drops_exactly_without_replacement():
    g = torch.Generator().manual_seed(0)
    a = dropout_active(1000, 0.5, g)
    assert a.dtype == torch.bool and int((~a).sum()) == 500
    assert dropout_active(1000, 0.0, g) is None
    b = dropout_active(1000, 0.5, g)
    assert not torch.equal(a, b)


def test_sh_neighbour_loss_zero_for_equal_sh_and_matches_formula():
    nbr = torch.tensor([[1, 2], [0, 2], [0, 1]])
    equal = torch.ones(3, 4, 3) * 0.7
    assert float(sh_neighbour_loss(equal, nbr)) == 0.0
    sh = torch.zeros(3, 1, 3)
    sh[0, 0, 0] = 1.0
    # Pairs (0,1), (0,2), (1,0), (2,0) differ by 1: 4 / (N K = 6).
    assert math.isclose(float(sh_neighbour_loss(sh, nbr)), 4 / 6, rel_tol=1e-6)


def test_mask_l1_and_composite():
    alpha = torch.zeros(1, 4, 4, 1)
    mask = torch.zeros(1, 4, 4, dtype=torch.bool)
    mask[0, :2] = True
    assert math.isclose(float(mask_l1(alpha, mask)), 0.5)
    img = torch.rand(1, 4, 4, 3)
    bg = torch.tensor([0.2, 0.4, 0.6])
    out = composite(img, mask, bg)
    torch.testing.assert_close(out[0, :2], img[0, :2])
    torch.testing.assert_close(out[0, 2:], bg.expand(2, 4, 3))


def test_fill_loss_is_mean_under_coverage_inside_the_mask():
    mask = torch.zeros(2, 4, 4)
    mask[:, 1:3, 1:3] = 1.0  # 8 object pixels over both views
    alpha = torch.full((2, 4, 4), 0.25)
    # Alpha outside the object costs nothing; inside, 1 - A averaged over the object's pixels.
    assert math.isclose(float(fill_loss(alpha, mask)), 0.75, rel_tol=1e-6)
    alpha[:, 1:3, 1:3] = 1.0
    assert float(fill_loss(alpha, mask)) == 0.0
    # Fractional (area-downsampled) coverage weights the rim pixels by how much of them is object.
    mask[0, 0, 0], alpha[0, 0, 0] = 0.5, 0.0
    assert math.isclose(float(fill_loss(alpha, mask)), 0.5 / 8.5, rel_tol=1e-6)
    assert float(fill_loss(alpha, torch.zeros(1, 4, 4))) == 0.0


def test_ssim_identity_and_photometric():
    a = torch.rand(2, 32, 32, 3)
    assert abs(float(ssim(a, a)) - 1) < 1e-5
    assert float(photometric_loss(a, a)) < 1e-5
    b = (a + 0.2 * torch.randn_like(a)).clamp(0, 1)
    assert float(ssim(a, b)) < 0.9
    l = photometric_loss(a, b)
    l1 = float((a - b).abs().mean())
    assert float(l) > 0.8 * l1
