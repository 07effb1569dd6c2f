"""USD export of a simulation body for Isaac Sim and other UsdPhysics readers (usd-core's `pxr`).

Layout (metres, kilograms, Z up, the object frame unchanged):

    /<body>                 Xform, default prim; UsdPhysics RigidBodyAPI + MassAPI (mass, centre of
                            mass, principal inertia and the rotation to its principal axes)
      /visual/<part>        one UsdGeom.Mesh per CAD part, named after it (made a valid identifier;
                            the CAD name is kept in customData "cad_part"), face colours baked from
                            the Gaussians; no collision
      /collision/<shape>    the collision shapes of `collision.py`, invisible: convex pieces as Meshes
                            with CollisionAPI + MeshCollisionAPI approximation "convexHull"; primitives
                            as UsdGeom Cube / Sphere / Cylinder / Capsule with CollisionAPI

The mass properties are written explicitly (not left to the importer to recompute from the
collision shapes, which would overstate the mass exactly as one convex hull does). The file is
written beside its destination, read back and checked (`check_usd`), then renamed into place.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from calibration.fileio import fsync_dir
from calibration.so3 import matrix_to_quat
from simulation.collision import Primitive
from simulation.mjcf import BodySpec


class UsdCheckError(ValueError):
    """A written USD file that does not read back as the body it should hold."""


def _identifier(name: str) -> str:
    from pxr import Tf

    return Tf.MakeValidIdentifier(str(name)) or "part"


def _unique(names: list[str]) -> list[str]:
    seen: dict[str, int] = {}
    out = []
    for n in names:
        k = seen.get(n, 0)
        seen[n] = k + 1
        out.append(n if k == 0 else f"{n}_{k}")
    return out


def _mesh(stage, path: str, vertices: np.ndarray, faces: np.ndarray):
    from pxr import UsdGeom, Vt

    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(vertices, np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.asarray(faces, np.int32).reshape(-1)))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    return mesh


def _primitive(stage, path: str, p: Primitive):
    from pxr import Gf, UsdGeom

    if p.kind == "box":
        geom = UsdGeom.Cube.Define(stage, path)
        geom.CreateSizeAttr(1.0)
        scale = 2.0 * np.asarray(p.size)
    elif p.kind == "sphere":
        geom = UsdGeom.Sphere.Define(stage, path)
        geom.CreateRadiusAttr(float(p.size[0]))
        scale = None
    else:  # cylinder and capsule: USD's height is the cylinder part's full length, along local z
        geom = (UsdGeom.Cylinder if p.kind == "cylinder" else UsdGeom.Capsule).Define(stage, path)
        geom.CreateRadiusAttr(float(p.size[0]))
        geom.CreateHeightAttr(float(2.0 * p.size[1]))
        geom.CreateAxisAttr(UsdGeom.Tokens.z)
        scale = None
    xf = UsdGeom.Xformable(geom)
    xf.AddTranslateOp().Set(Gf.Vec3d(*map(float, p.transform[:3, 3])))
    w, x, y, z = matrix_to_quat(p.transform[:3, :3])
    xf.AddOrientOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Quatd(float(w), float(x), float(y), float(z)))
    if scale is not None:
        xf.AddScaleOp().Set(Gf.Vec3f(*map(float, scale)))
    return geom


def principal_frame(inertia: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(principal moments [3] ascending, quaternion wxyz [4] of the rotation whose columns are the
    principal axes) of a symmetric inertia [3, 3]; the rotation is proper (det +1)."""
    moments, axes = np.linalg.eigh(np.asarray(inertia, np.float64))
    if np.linalg.det(axes) < 0:
        axes[:, 2] *= -1
    return moments, matrix_to_quat(axes)


def usd_stage(body: BodySpec):
    """An in-memory Usd.Stage holding `body` (see the module docstring)."""
    import trimesh
    from pxr import Gf, Usd, UsdGeom, UsdPhysics, Vt

    a, col, m = body.asset, body.collision, body.asset.mass
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdPhysics.SetStageKilogramsPerUnit(stage, 1.0)
    root_path = "/" + _identifier(a.name)
    root = UsdGeom.Xform.Define(stage, root_path).GetPrim()
    stage.SetDefaultPrim(root)
    UsdPhysics.RigidBodyAPI.Apply(root)
    mass = UsdPhysics.MassAPI.Apply(root)
    mass.CreateMassAttr(float(m.mass))
    mass.CreateDensityAttr(float(a.density.value))
    mass.CreateCenterOfMassAttr(Gf.Vec3f(*map(float, m.center_of_mass)))
    moments, q = principal_frame(m.inertia)
    mass.CreateDiagonalInertiaAttr(Gf.Vec3f(*map(float, moments)))
    mass.CreatePrincipalAxesAttr(Gf.Quatf(float(q[0]), float(q[1]), float(q[2]), float(q[3])))
    root.SetCustomDataByKey("cadsplat:volume_m3", float(m.volume))
    root.SetCustomDataByKey("cadsplat:density_source", a.density.source)

    UsdGeom.Scope.Define(stage, f"{root_path}/visual")
    names = _unique([_identifier(n) for n in a.part_names])
    for p, (name, cad_name) in enumerate(zip(names, a.part_names)):
        sel = np.flatnonzero(a.face_part == p)
        if sel.size == 0:
            continue
        used, local = np.unique(a.faces[sel], return_inverse=True)
        mesh = _mesh(stage, f"{root_path}/visual/{name}", a.vertices[used], local.reshape(-1, 3))
        colors = mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.uniform)
        colors.Set(Vt.Vec3fArray.FromNumpy(np.asarray(a.face_rgb[sel], np.float32)))
        mesh.GetPrim().SetCustomDataByKey("cad_part", str(cad_name))

    UsdGeom.Scope.Define(stage, f"{root_path}/collision")
    shapes = []
    for i, piece in enumerate(col.pieces):
        hull = trimesh.convex.convex_hull(np.asarray(piece, np.float64))
        geom = _mesh(stage, f"{root_path}/collision/hull_{i}", hull.vertices, hull.faces)
        UsdPhysics.MeshCollisionAPI.Apply(geom.GetPrim()).CreateApproximationAttr(UsdPhysics.Tokens.convexHull)
        shapes.append(geom)
    for i, p in enumerate(col.primitives):
        shapes.append(_primitive(stage, f"{root_path}/collision/{p.kind}_{i}", p))
    for geom in shapes:
        UsdPhysics.CollisionAPI.Apply(geom.GetPrim())
        UsdGeom.Imageable(geom).CreatePurposeAttr(UsdGeom.Tokens.guide)
    root.SetCustomDataByKey("cadsplat:collision", {"kind": col.kind, "volume_error": float(col.volume_error)})
    stage.GetRootLayer().customLayerData = {"generator": "cadsplat"}
    return stage


def check_usd(path: str | os.PathLike, body: BodySpec) -> None:
    """Read `path` back with pxr and check it holds `body`: a rigid body with the mass, centre of
    mass and principal inertia of the asset, the asset's triangles, and one collision prim per
    collision shape. Raises UsdCheckError naming the first mismatch."""
    from pxr import Usd, UsdGeom, UsdPhysics

    stage = Usd.Stage.Open(str(path))
    if stage is None:
        raise UsdCheckError(f"{path}: pxr cannot open the file just written")
    root = stage.GetDefaultPrim()
    if not (root and root.HasAPI(UsdPhysics.RigidBodyAPI) and root.HasAPI(UsdPhysics.MassAPI)):
        raise UsdCheckError(f"{path}: the default prim is not a rigid body with a mass")
    m = body.asset.mass
    api = UsdPhysics.MassAPI(root)
    if not np.isclose(api.GetMassAttr().Get(), m.mass, rtol=1e-6):
        raise UsdCheckError(f"{path}: mass {api.GetMassAttr().Get()} kg, expected {m.mass}")
    if not np.allclose(np.array(api.GetCenterOfMassAttr().Get()), m.center_of_mass, atol=1e-6):
        raise UsdCheckError(f"{path}: centre of mass differs from the asset's")
    if not np.allclose(np.array(api.GetDiagonalInertiaAttr().Get()), m.principal_moments, rtol=1e-5, atol=1e-12):
        raise UsdCheckError(f"{path}: principal inertia differs from the asset's")
    tris = []
    for prim in Usd.PrimRange(root.GetChild("visual")):
        if prim.IsA(UsdGeom.Mesh):
            mesh = UsdGeom.Mesh(prim)
            pts = np.array(mesh.GetPointsAttr().Get(), np.float64)
            tris.append(pts[np.array(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)])
    got = np.concatenate(tris) if tris else np.zeros((0, 3, 3))
    want = body.asset.vertices[body.asset.faces]
    if got.shape != want.shape or not np.allclose(_canonical(got), _canonical(want), atol=1e-6):
        raise UsdCheckError(f"{path}: the visual meshes are not the asset's {len(want)} triangles")
    n_col = sum(1 for prim in Usd.PrimRange(root.GetChild("collision")) if prim.HasAPI(UsdPhysics.CollisionAPI))
    if n_col != body.collision.hull_count + len(body.collision.primitives):
        raise UsdCheckError(f"{path}: {n_col} collision prims, expected {body.collision.hull_count + len(body.collision.primitives)}")


def _canonical(tris: np.ndarray) -> np.ndarray:
    """Triangles [T, 3, 3] in an order-free form that keeps winding: each rolled to start at its
    lexicographically smallest corner, then the triangles sorted. Returns [T, 9]."""
    t = np.round(np.asarray(tris, np.float64), 9)
    first = [min(range(3), key=lambda i: tuple(tri[i])) for tri in t]
    keys = np.stack([np.roll(tri, -k, axis=0) for tri, k in zip(t, first)]).reshape(len(t), 9) if len(t) else t.reshape(0, 9)
    return keys[np.lexsort(keys.T[::-1])]


def write_usd(path: str | os.PathLike, body: BodySpec) -> Path:
    """Write `body` as a USD file (.usda text or .usd/.usdc binary) beside `path`, check it reads back
    as the body (`check_usd`), then rename it into place. Returns `path`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        stage = usd_stage(body)  # held: the layer lives only as long as its stage
        if not stage.GetRootLayer().Export(tmp):
            raise UsdCheckError(f"{path}: pxr could not write the file")
        check_usd(tmp, body)
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
        fsync_dir(path.parent)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path
