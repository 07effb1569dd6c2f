"""MJCF package writer: one directory with `model.xml`, mesh files and textures for one twin or a scene.

Each body carries two kinds of geoms:
- the visual mesh (the repaired, closed and outward-oriented deformed CAD mesh, textured with colours
  baked from the Gaussians so MuJoCo's own viewer shows the real object). It alone gives the body
  its mass and inertia, with `inertia="exact"` (MuJoCo's default would use the convex hull's
  volume) at the asset's density; it does not collide (contype = conaffinity = 0).
- the collision geometry (`collision.py`): primitives, the hull or convex pieces, massless.
Body frame = object frame, so a body's simulated pose moves the twin's Gaussians directly.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calibration.fileio import atomic_write_bytes, atomic_write_json, encode_png, fsync_dir, sha256_file
from calibration.so3 import matrix_to_quat
from simulation.asset import SimAsset
from simulation.collision import CollisionGeometry

MODEL_XML = "model.xml"
MANIFEST_JSON = "manifest.json"


@dataclass(frozen=True)
class ContactParams:
    """Contact model written into the MJCF (MuJoCo's soft contacts).

    solref (timeconst, dampratio): timeconst 2x the timestep, critically damped, so objects settle
    without bouncing through each other; solimp (0.95, 0.99, 1 mm) makes resting penetration
    micrometres. condim 6 with a little rolling friction lets round things come to rest.
    """

    friction: tuple[float, float, float] = (0.8, 0.005, 0.0005)
    condim: int = 6
    solref: tuple[float, float] = (0.002, 1.0)
    solimp: tuple[float, float, float, float, float] = (0.95, 0.99, 0.001, 0.5, 2.0)
    margin: float = 0.0


@dataclass(frozen=True)
class SimOptions:
    """Global physics: timestep (s), gravity (m/s^2), integrator and friction cone."""

    timestep: float = 0.001
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)
    integrator: str = "implicitfast"
    cone: str = "elliptic"
    impratio: float = 10.0
    floor: bool = True
    floor_size: float = 5.0
    contact: ContactParams = field(default_factory=ContactParams)


@dataclass(frozen=True)
class BodySpec:
    """A rigid body to place: its asset, collision geometry, initial pose (pos [3] m, quat [4] wxyz)
    and whether it is welded to the world (a fixture) rather than free."""

    asset: SimAsset
    collision: CollisionGeometry
    pos: np.ndarray
    quat: np.ndarray
    fixed: bool = False


def _fmt(values) -> str:
    return " ".join(f"{float(x):.9g}" for x in np.asarray(values, np.float64).reshape(-1))


def visual_obj(vertices: np.ndarray, faces: np.ndarray, atlas: int) -> bytes:
    """OBJ text of the mesh with one texel per face: face i samples texel (i mod atlas, i div atlas)."""
    f = np.asarray(faces, np.int64)
    i = np.arange(len(f))
    uv = np.stack([(i % atlas + 0.5) / atlas, 1.0 - (i // atlas + 0.5) / atlas], 1)
    lines = ["# cadsplat visual mesh: metres, object frame; texcoord i is face i's baked colour"]
    lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in np.asarray(vertices, np.float64)]
    lines += [f"vt {u:.7f} {v:.7f}" for u, v in uv]
    lines += [f"f {a + 1}/{k + 1} {b + 1}/{k + 1} {c + 1}/{k + 1}" for k, (a, b, c) in enumerate(f)]
    return ("\n".join(lines) + "\n").encode()


def face_atlas(face_rgb: np.ndarray) -> np.ndarray:
    """Square uint8 texture [A, A, 3] holding one texel per face, row-major from the top."""
    n = len(face_rgb)
    atlas = max(int(np.ceil(np.sqrt(n))), 1)
    tex = np.full((atlas * atlas, 3), 128, np.uint8)
    tex[:n] = np.clip(np.asarray(face_rgb) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return tex.reshape(atlas, atlas, 3)


def hull_obj(points: np.ndarray) -> bytes:
    """OBJ text of the convex hull of points [M, 3] (outward faces)."""
    import trimesh

    hull = trimesh.convex.convex_hull(np.asarray(points, np.float64))
    lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in hull.vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in hull.faces]
    return ("\n".join(lines) + "\n").encode()


def _collision_geoms(body: ET.Element, assets: ET.Element, spec: BodySpec, files: dict[str, bytes]) -> None:
    name, col = spec.asset.name, spec.collision
    common = {"group": "3", "mass": "0", "rgba": "0.2 0.6 1 0.3"}
    for i, p in enumerate(col.primitives):
        ET.SubElement(
            body,
            "geom",
            name=f"{name}_collision_{p.kind}_{i}",
            type=p.kind,
            size=_fmt(p.size),
            pos=_fmt(p.transform[:3, 3]),
            quat=_fmt(matrix_to_quat(p.transform[:3, :3])),
            **common,
        )
    for i, piece in enumerate(col.pieces):
        mesh_name = f"{name}_collision_{i}"
        files[f"meshes/{mesh_name}.obj"] = hull_obj(piece)
        ET.SubElement(assets, "mesh", name=mesh_name, file=f"{mesh_name}.obj", inertia="convex")
        ET.SubElement(body, "geom", name=mesh_name, type="mesh", mesh=mesh_name, **common)


def mjcf_document(bodies: list[BodySpec], options: SimOptions = SimOptions(), model_name: str = "cadsplat") -> tuple[str, dict[str, bytes]]:
    """The MJCF XML text and the files it references (relative path -> bytes)."""
    names = [b.asset.name for b in bodies]
    if len(set(names)) != len(names):
        raise ValueError(f"body names must be unique, got {', '.join(names)}")
    c = options.contact
    root = ET.Element("mujoco", model=model_name)
    ET.SubElement(root, "compiler", angle="radian", meshdir="meshes", texturedir="textures", autolimits="true")
    opt = ET.SubElement(
        root,
        "option",
        timestep=_fmt(options.timestep),
        gravity=_fmt(options.gravity),
        integrator=options.integrator,
        cone=options.cone,
        impratio=_fmt(options.impratio),
    )
    ET.SubElement(opt, "flag", energy="enable")
    default = ET.SubElement(root, "default")
    ET.SubElement(
        default,
        "geom",
        condim=str(c.condim),
        friction=_fmt(c.friction),
        solref=_fmt(c.solref),
        solimp=_fmt(c.solimp),
        margin=_fmt(c.margin),
    )
    ET.SubElement(ET.SubElement(root, "visual"), "headlight", ambient="0.5 0.5 0.5", diffuse="0.5 0.5 0.5")
    assets = ET.SubElement(root, "asset")
    world = ET.SubElement(root, "worldbody")
    ET.SubElement(world, "light", pos="0 0 3", dir="0 0 -1", directional="true")
    files: dict[str, bytes] = {}
    if options.floor:
        ET.SubElement(
            assets,
            "texture",
            name="floor_grid",
            type="2d",
            builtin="checker",
            rgb1="0.75 0.75 0.75",
            rgb2="0.6 0.6 0.6",
            width="256",
            height="256",
        )
        ET.SubElement(assets, "material", name="floor", texture="floor_grid", texrepeat="8 8", reflectance="0.05")
        ET.SubElement(
            world, "geom", name="floor", type="plane", size=f"{options.floor_size:g} {options.floor_size:g} 0.1", material="floor"
        )
    for spec in bodies:
        a = spec.asset
        tex = face_atlas(a.face_rgb)
        files[f"meshes/{a.name}.obj"] = visual_obj(a.vertices, a.faces, tex.shape[0])
        files[f"textures/{a.name}.png"] = encode_png(tex)
        ET.SubElement(assets, "texture", name=f"{a.name}_texture", type="2d", file=f"{a.name}.png")
        ET.SubElement(assets, "material", name=f"{a.name}_material", texture=f"{a.name}_texture", specular="0.2")
        ET.SubElement(assets, "mesh", name=a.name, file=f"{a.name}.obj", inertia="exact")
        body = ET.SubElement(world, "body", name=a.name, pos=_fmt(spec.pos), quat=_fmt(spec.quat))
        if not spec.fixed:
            ET.SubElement(body, "freejoint", name=f"{a.name}_free")
        ET.SubElement(
            body,
            "geom",
            name=f"{a.name}_visual",
            type="mesh",
            mesh=a.name,
            material=f"{a.name}_material",
            density=_fmt(a.density.value),
            contype="0",
            conaffinity="0",
            group="1",
        )
        _collision_geoms(body, assets, spec, files)
    ET.indent(root)
    return ET.tostring(root, encoding="unicode") + "\n", files


def body_manifest(b: BodySpec) -> dict:
    """A body's physics as the manifest records it: density and where it came from, the volume the
    mass came from, mass, centre of mass, inertia (full and principal), the repair, the collision."""
    a, c, m = b.asset, b.collision, b.asset.mass
    return {
        "name": a.name,
        "parts": list(a.part_names),
        "density": {"kg_m3": a.density.value, "material": a.density.material, "source": a.density.source},
        "volume_m3": m.volume,
        "volume_source": "closed repaired mesh (divergence theorem)",
        "mass_kg": m.mass,
        "center_of_mass": m.center_of_mass,
        "inertia_kg_m2": m.inertia,
        "principal_inertia_kg_m2": m.principal_moments,
        "principal_axes": m.principal_axes,
        "repair": {**vars(a.repair), "summary": a.repair.summary()},
        "collision": {
            "kind": c.kind,
            "primitives": [p.kind for p in c.primitives],
            "hulls": c.hull_count,
            "hull_budget": c.hull_budget,
            "volume_m3": c.volume,
            "volume_error": c.volume_error,
            "hausdorff_m": c.hausdorff if np.isfinite(c.hausdorff) else None,
            "seconds": c.seconds,
            "notes": list(c.notes),
        },
        "pose": {"pos": b.pos, "quat_wxyz": b.quat, "fixed": b.fixed},
    }


def write_mjcf_package(
    out_dir: str | os.PathLike, bodies: list[BodySpec], options: SimOptions = SimOptions(), extra: dict | None = None
) -> Path:
    """Write the MJCF package (every file atomically, `manifest.json` last with their sha256, each
    body's mass properties and collision choice, and `extra`'s entries). Returns the path of `model.xml`."""
    out = Path(out_dir)
    xml, files = mjcf_document(bodies, options, model_name=out.name or "cadsplat")
    for sub in ("meshes", "textures"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    for rel, data in files.items():
        atomic_write_bytes(out / rel, data)
    atomic_write_bytes(out / MODEL_XML, xml.encode())
    for sub in ("meshes", "textures"):
        fsync_dir(out / sub)
    manifest = {
        "format": "cadsplat-mjcf/1",
        "model": MODEL_XML,
        "options": {"timestep": options.timestep, "gravity": list(options.gravity), "integrator": options.integrator, "cone": options.cone},
        "contact": {k: getattr(options.contact, k) for k in ("friction", "condim", "solref", "solimp", "margin")},
        "bodies": [body_manifest(b) for b in bodies],
        **(extra or {}),
        "sha256": {rel: sha256_file(out / rel) for rel in [MODEL_XML, *files]},
    }
    atomic_write_json(out / MANIFEST_JSON, manifest)
    return out / MODEL_XML
