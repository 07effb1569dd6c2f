"""Small twins for simulation tests, built directly (splats sampled on a mesh), not reconstructed."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from calibration.camera import look_at_c2w
from calibration.sim3 import Sim3
from reconstruction.gaussians import Gaussians
from reconstruction.mesh_io import MeshParts
from reconstruction.splats import init_splats, rgb_to_sh_dc
from reconstruction.twin import Twin, TwinCamera, save_twin


def assemble(pieces: list[tuple[str, trimesh.Trimesh, tuple[float, float, float]]]) -> tuple[MeshParts, np.ndarray]:
    """Named coloured meshes -> MeshParts (one part each) and face colours [F, 3]."""
    verts, faces, part, rgb = [], [], [], []
    offset = 0
    for i, (_, mesh, colour) in enumerate(pieces):
        verts.append(mesh.vertices)
        faces.append(mesh.faces + offset)
        part.append(np.full(len(mesh.faces), i))
        rgb.append(np.tile(colour, (len(mesh.faces), 1)))
        offset += len(mesh.vertices)
    names = [name for name, _, _ in pieces]
    return MeshParts(np.concatenate(verts), np.concatenate(faces), np.concatenate(part), names), np.concatenate(rgb)


def box(extents, centre=(0, 0, 0)) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents).apply_translation(centre)


def wheel(centre, radius=0.012, width=0.01) -> trimesh.Trimesh:
    m = trimesh.creation.cylinder(radius=radius, height=width, sections=24)
    m.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    return m.apply_translation(centre)


def skateboard() -> tuple[MeshParts, np.ndarray]:
    """A deck (green) on four red wheels: five parts, wheels below the deck's corners."""
    pieces = [("deck", box([0.24, 0.08, 0.012], (0, 0, 0.03)), (0.1, 0.6, 0.2))]
    for i, (x, y) in enumerate([(-0.08, -0.035), (-0.08, 0.035), (0.08, -0.035), (0.08, 0.035)]):
        pieces.append((f"wheel_{i}", wheel((x, y, 0.012)), (0.85, 0.1, 0.1)))
    return assemble(pieces)


def hammer() -> tuple[MeshParts, np.ndarray]:
    """A brown handle with a grey steel-coloured head: two parts (a T)."""
    return assemble(
        [
            ("handle", box([0.14, 0.02, 0.016], (0, 0, 0)), (0.55, 0.35, 0.15)),
            ("head", box([0.03, 0.07, 0.024], (0.085, 0, 0)), (0.6, 0.6, 0.65)),
        ]
    )


def make_twin(
    root: Path,
    model_id: str,
    parts: MeshParts,
    face_rgb: np.ndarray,
    n: int = 3000,
    seed: int = 0,
    sim3_rig_to_object: Sim3 | None = None,
) -> Path:
    """Save a twin of `parts` with `n` coloured splats (SH degree 1, a small view-dependent term), registered by
    `sim3_rig_to_object` (default: the identity)."""
    sim3 = sim3_rig_to_object or Sim3(1.0, np.eye(3), np.zeros(3))
    s = init_splats(parts.vertices, parts.faces, n, sh_degree=1, face_part=parts.face_part, seed=seed)
    sh = s.gaussians.sh.copy()
    sh[:, 0] = rgb_to_sh_dc(face_rgb[s.face_index])
    sh[:, 1:] = 0.02
    cams = []
    centre = parts.vertices.mean(0)
    for i, az in enumerate(np.linspace(0, 2 * np.pi, 4, endpoint=False)):
        eye = centre + 0.5 * np.array([np.cos(az), np.sin(az), 0.5])
        k = np.array([[200.0, 0, 80], [0, 200.0, 60], [0, 0, 1]])
        cams.append(TwinCamera(f"images/view_{i}.png", f"cam{i}", k, 160, 120, look_at_c2w(eye, centre)))
    twin = Twin(
        model_id=model_id,
        sim3_rig_to_object_init=sim3,
        sim3_rig_to_object=sim3,
        cameras=cams,
        preset="test",
        choices={},
        timings_s={},
        losses={},
        gaussians=Gaussians(s.means, s.gaussians.quats, s.gaussians.log_scales, np.full(n, 4.0, np.float32), sh),
        means_canonical=s.means,
        face_index=s.face_index,
        barycentrics=s.barycentrics,
        part_label=s.part_label,
        part_names=parts.part_names,
    )
    return save_twin(twin, root / model_id, mesh_cad=parts, mesh_deformed=parts)
