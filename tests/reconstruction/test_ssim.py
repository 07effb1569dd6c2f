"""The fused SSIM map: the same value and gradients as SSIM through torch ops and autograd."""

from __future__ import annotations

import pytest
import torch

from reconstruction.ssim import _ssim_map_torch, dssim_l1_sums, gaussian_window, ssim_map


def _pair(dtype: torch.dtype, shape=(2, 23, 31, 3), seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    a = torch.rand(shape, generator=gen, dtype=dtype)
    b = (a + 0.3 * torch.randn(shape, generator=gen, dtype=dtype)).clamp(0, 1)
    b[:, : shape[1] // 3] = a[:, : shape[1] // 3]  # identical rows: S = 1 there, its gradient 0
    return a, b


def _value_and_grads(fn, a, b, weight, want=(True, True)):
    x, y = a.clone().requires_grad_(want[0]), b.clone().requires_grad_(want[1])
    (fn(x, y) * weight).sum().backward()
    return fn(x, y).detach(), x.grad, y.grad


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
@pytest.mark.parametrize("shape", [(2, 23, 31, 3), (1, 5, 7, 3)])  # the second is smaller than the window
def test_map_and_gradients_match_autograd_through_torch_ops(dtype, tol, shape):
    a, b = _pair(dtype, shape)
    weight = torch.rand(shape[0], 3, *shape[1:3], generator=torch.Generator().manual_seed(1), dtype=dtype)
    reference = lambda x, y: _ssim_map_torch(x, y, gaussian_window(11, 1.5, dtype))  # noqa: E731
    for got, want in zip(_value_and_grads(ssim_map, a, b, weight), _value_and_grads(reference, a, b, weight)):
        assert got.shape == want.shape
        assert float((got - want).abs().max()) <= tol


def test_gradient_only_for_the_inputs_that_want_it():
    a, b = _pair(torch.float32)
    weight = torch.ones(2, 3, 23, 31)
    _, gx, gy = _value_and_grads(ssim_map, a, b, weight, want=(True, False))
    assert gx is not None and gy is None
    reference = _value_and_grads(lambda x, y: _ssim_map_torch(x, y, gaussian_window(11, 1.5)), a, b, weight, (True, False))
    assert float((gx - reference[1]).abs().max()) <= 1e-5


def test_identical_images_score_one_with_zero_gradient():
    a, _ = _pair(torch.float32)
    x = a.clone().requires_grad_()
    m = ssim_map(x, a)
    assert float((m.detach() - 1).abs().max()) < 1e-5
    m.sum().backward()
    assert float(x.grad.abs().max()) < 1e-4


def test_an_even_window_is_one_sentence():
    a, b = _pair(torch.float32)
    with pytest.raises(ValueError, match="positive odd number"):
        ssim_map(a, b, window=10)


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-10), (torch.float32, 2e-4)])
def test_fused_sums_match_the_map_and_l1_through_torch_ops(dtype, tol):
    # The training loss's (sum 1 - SSIM, sum |a - b|) in one pass, against torch ops; identical rows make |a - b| = 0
    # there (no L1 gradient), as torch's abs.
    a, b = _pair(dtype)
    window = gaussian_window(11, 1.5, dtype)
    x, y = a.clone().requires_grad_(True), b.clone().requires_grad_(True)
    dssim_sum, l1_sum = dssim_l1_sums(x, y)
    (0.3 * dssim_sum + 0.7 * l1_sum).backward()
    rx, ry = a.clone().requires_grad_(True), b.clone().requires_grad_(True)
    r_ssim, r_l1 = (1 - _ssim_map_torch(rx, ry, window)).sum(), (rx - ry).abs().sum()
    (0.3 * r_ssim + 0.7 * r_l1).backward()
    assert abs(dssim_sum.item() - r_ssim.item()) <= tol * r_ssim.item()
    assert abs(l1_sum.item() - r_l1.item()) <= tol * r_l1.item()
    assert float((x.grad - rx.grad).abs().max()) <= tol and float((y.grad - ry.grad).abs().max()) <= tol


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32, torch.float16])
def test_window_sums_read_from_the_images_equal_the_sums_of_the_crops(dtype):
    """Each view's window read in place (and its gradient written in place, zero outside it) gives exactly what
    cropping first gave, on the kernels and on the torch-op path (float16 takes it)."""
    gen = torch.Generator().manual_seed(7)
    a, b = torch.rand(3, 40, 52, 3, generator=gen), torch.rand(3, 40, 52, 3, generator=gen)
    a, b = a.to(dtype), b.to(dtype)
    corners, h, w = torch.tensor([[0, 0], [9, 20], [40 - 23, 52 - 31]]), 23, 31
    x, y = a.clone().requires_grad_(True), b.clone().requires_grad_(True)
    dssim_sum, l1_sum = dssim_l1_sums(x, y, windows=(corners, h, w))
    (0.3 * dssim_sum + 0.7 * l1_sum).backward()
    rx, ry = a.clone().requires_grad_(True), b.clone().requires_grad_(True)
    crop = lambda t: torch.stack([t[c, i : i + h, j : j + w] for c, (i, j) in enumerate(corners.tolist())])  # noqa: E731
    r_dssim, r_l1 = dssim_l1_sums(crop(rx), crop(ry))
    (0.3 * r_dssim + 0.7 * r_l1).backward()
    assert dssim_sum.item() == r_dssim.item() and l1_sum.item() == r_l1.item()
    assert torch.equal(x.grad, rx.grad) and torch.equal(y.grad, ry.grad)
    outside = torch.ones(3, 40, 52, dtype=torch.bool)
    for c, (i, j) in enumerate(corners.tolist()):
        outside[c, i : i + h, j : j + w] = False
    assert x.grad[outside].abs().max() == 0 and x.grad[~outside].abs().max() > 0
