"""One set of 3D Gaussians, and the one way to render it.

`Gaussians` holds 3DGS's stored parameterisation (means, wxyz quats, log-scales, opacity logits,
SH coefficients). The engine trains it, the baselines produce it, a `Twin` holds it, evaluation,
`cadsplat render` and the simulation's rigid-body renders consume it. The arrays are numpy float32
when stored, or torch tensors inside a training step (the activation keeps their gradients).

`render` is the single rendering contract: colour composited over a background plus alpha, as
tensors, for a batch of pinhole cameras. PNG-style straight alpha is `straight_rgba` of that.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from calibration.camera import Camera
from calibration.sim3 import Sim3
from reconstruction.render import eval_sh, num_sh_bases, rasterize

Array = np.ndarray | torch.Tensor
WHITE = (1.0, 1.0, 1.0)
# Screen-space variance (px^2) added to each splat's 2D covariance when it is drawn: 3DGS's (and gsplat's) 0.3.
# A set fitted with another value carries it (`Gaussians.eps2d`), so that every render draws what was fitted.
EPS2D_3DGS = 0.3
# Directions the SH rotation is solved on: more than the 16 degree-3 bases, well spread.
_SH_PROBE_DIRECTIONS = 64


@dataclass(frozen=True)
class Gaussians:
    """N Gaussians: means [N, 3], quats [N, 4] wxyz (any norm), log_scales [N, 3], opacity_logits [N],
    sh [N, K, 3] with K = (sh_degree + 1)^2 (DC in the 3DGS convention: colour = 0.5 + C0 * sh[:, 0]); eps2d, the
    screen-space variance (px^2) the set was fitted with and is drawn with."""

    means: Array
    quats: Array
    log_scales: Array
    opacity_logits: Array
    sh: Array
    eps2d: float = EPS2D_3DGS

    def __post_init__(self) -> None:
        if not (math.isfinite(self.eps2d) and self.eps2d >= 0.0):
            raise ValueError(f"Gaussians eps2d must be a finite variance >= 0 px^2, got {self.eps2d}")
        n = self.means.shape[0]
        k = self.sh.shape[1] if self.sh.ndim == 3 else -1
        expected = {"means": (n, 3), "quats": (n, 4), "log_scales": (n, 3), "opacity_logits": (n,), "sh": (n, k, 3)}
        for name, shape in expected.items():
            if tuple(getattr(self, name).shape) != shape:
                raise ValueError(f"Gaussians {name} has shape {tuple(getattr(self, name).shape)}, expected {shape}")
        if num_sh_bases(round(k**0.5) - 1) != k:
            raise ValueError(f"Gaussians sh holds {k} coefficients per colour, not (degree + 1)^2 for a degree 0..3")

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return round(self.sh.shape[1] ** 0.5) - 1

    @staticmethod
    def from_arrays(means, quats, log_scales, opacity_logits, sh, eps2d: float = EPS2D_3DGS) -> Gaussians:
        """float32 numpy copies of array-likes (a twin read from disk, a trained model's detached state)."""

        def f32(a) -> np.ndarray:
            a = a.detach().cpu().numpy() if isinstance(a, torch.Tensor) else a
            return np.array(a, dtype=np.float32)

        return Gaussians(f32(means), f32(quats), f32(log_scales), f32(opacity_logits), f32(sh), float(eps2d))

    def activated(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The rasterizer's inputs, float32 tensors: means [N, 3], quats [N, 4], scales [N, 3] = exp(log_scales),
        opacities [N] = sigmoid(opacity_logits), sh [N, K, 3]. Tensors keep their autograd graph; numpy
        arrays are wrapped (the activations are new tensors, so nothing written through them reaches the arrays)."""

        def t(a: Array) -> torch.Tensor:
            return torch.as_tensor(a, dtype=torch.float32)

        return t(self.means), t(self.quats), torch.exp(t(self.log_scales)), torch.sigmoid(t(self.opacity_logits)), t(self.sh)

    def subset(self, index: Array) -> Gaussians:
        """The Gaussians selected by `index` ([M] int or [N] bool)."""
        return Gaussians(
            self.means[index], self.quats[index], self.log_scales[index], self.opacity_logits[index], self.sh[index], self.eps2d
        )

    def with_sh_degree(self, degree: int) -> Gaussians:
        """SH cut to or zero-padded up to `degree` (a degree-0 twin read by a viewer that expects degree 3)."""
        k = num_sh_bases(degree)
        sh = np.asarray(self.sh)
        out = np.zeros((len(self), k, 3), np.float32)
        out[:, : min(k, sh.shape[1])] = sh[:, :k]
        return Gaussians(self.means, self.quats, self.log_scales, self.opacity_logits, out, self.eps2d)

    def transformed(self, sim3: Sim3 | np.ndarray) -> Gaussians:
        """The Gaussians moved by a Sim(3) (or a rigid [4, 4]): means s R x + t, orientations R q,
        scales times s, and the SH turned with the body so every view sees the colour it saw before."""
        t = sim3 if isinstance(sim3, Sim3) else Sim3.from_matrix(np.asarray(sim3, np.float64))
        turn = Rotation.from_matrix(t.rotation)
        quats = (turn * Rotation.from_quat(np.asarray(self.quats, np.float64), scalar_first=True)).as_quat(scalar_first=True)
        sh = np.einsum("ij,njc->nic", sh_rotation(t.rotation, self.sh_degree), np.asarray(self.sh, np.float64))
        return Gaussians(
            t.apply(self.means).astype(np.float32),
            quats.astype(np.float32),
            (np.asarray(self.log_scales, np.float64) + np.log(t.scale)).astype(np.float32),
            np.asarray(self.opacity_logits, np.float32),
            sh.astype(np.float32),
            self.eps2d,
        )

    @staticmethod
    def concatenate(sets: Sequence[Gaussians]) -> Gaussians:
        """One set of several (SH padded to the highest degree among them). One render draws with one dilation: the
        smallest eps2d among them, so that the bare-mesh splats a simulation adds (never fitted, 3DGS's default) do
        not blur a twin fitted with less; a set fitted with more then draws a little thinner."""
        degree = max(g.sh_degree for g in sets)
        sets = [g.with_sh_degree(degree) for g in sets]
        cat = lambda name: np.concatenate([np.asarray(getattr(g, name), np.float32) for g in sets])  # noqa: E731
        return Gaussians(cat("means"), cat("quats"), cat("log_scales"), cat("opacity_logits"), cat("sh"), min(g.eps2d for g in sets))


def sh_basis(degree: int, dirs: np.ndarray) -> np.ndarray:
    """Real SH basis values [M, K] along directions [M, 3], as the rasterizer evaluates colour."""
    k = num_sh_bases(degree)
    unit = torch.eye(k, dtype=torch.float64)[:, :, None].expand(k, k, 3)
    with torch.no_grad():
        values = eval_sh(degree, unit[None], torch.as_tensor(dirs, dtype=torch.float64)[:, None, :])
    return values[..., 0].numpy()


def sh_rotation(rotation: np.ndarray, degree: int) -> np.ndarray:
    """[K, K] map of SH coefficients of a body turned by rotation [3, 3]: sh' = M @ sh per colour, so
    that SH'(d) = SH(R^T d). Each band is closed under rotation, so solving on sample directions is exact."""
    n = _SH_PROBE_DIRECTIONS
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (1.0 + 5.0**0.5) * i
    dirs = np.stack([np.sqrt(1 - z**2) * np.cos(phi), np.sqrt(1 - z**2) * np.sin(phi), z], -1)
    basis = sh_basis(degree, dirs)
    turned = sh_basis(degree, dirs @ np.asarray(rotation, np.float64))
    return np.linalg.lstsq(basis, turned, rcond=None)[0]


def camera_batch(cameras: Camera | Sequence[Camera]) -> tuple[torch.Tensor, torch.Tensor, int, int]:
    """viewmats [V, 4, 4], Ks [V, 3, 3] (float32) and the shared image size of pinhole cameras."""
    cams = [cameras] if isinstance(cameras, Camera) else list(cameras)
    sizes = {(c.width, c.height) for c in cams}
    if len(sizes) != 1:
        raise ValueError(f"cameras of one render must share an image size, got {sorted(sizes)}")
    ((width, height),) = sizes
    viewmats = torch.as_tensor(np.stack([c.viewmat for c in cams]), dtype=torch.float32)
    Ks = torch.as_tensor(np.stack([c.K for c in cams]), dtype=torch.float32)
    return viewmats, Ks, width, height


def render(
    gaussians: Gaussians,
    viewmats: Array,
    Ks: Array,
    width: int,
    height: int,
    background: Sequence[float] | Array | None = WHITE,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Renders `gaussians` into V pinhole cameras.

    viewmats [V, 4, 4] world-to-camera (may carry gradients, as in test-time pose refinement),
    Ks [V, 3, 3]; background [3] or [V, 3], or None for black (the colour is then premultiplied).
    Returns rgb [V, H, W, 3] composited over the background and alpha [V, H, W].
    """
    means, quats, scales, opacities, sh = gaussians.activated()
    viewmats = torch.as_tensor(viewmats, dtype=torch.float32)
    bg = None if background is None else torch.as_tensor(background, dtype=torch.float32).expand(len(viewmats), 3)
    rgb, alpha, _ = rasterize(
        means,
        quats,
        scales,
        opacities,
        sh,
        viewmats,
        torch.as_tensor(Ks, dtype=torch.float32),
        width,
        height,
        sh_degree=gaussians.sh_degree,
        backgrounds=bg,
        eps2d=gaussians.eps2d,
    )
    return rgb, alpha[..., 0]


def straight_rgba(rgb: torch.Tensor, alpha: torch.Tensor) -> np.ndarray:
    """RGBA [..., H, W, 4] float32 with straight alpha (as PNG stores it) from a render over black."""
    a = alpha.detach().numpy()[..., None]
    straight = np.where(a > 1e-4, rgb.detach().numpy() / np.maximum(a, 1e-4), 0.0)
    return np.concatenate([np.clip(straight, 0, 1), a], -1).astype(np.float32)
