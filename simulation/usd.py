"""USD export of a simulation body for Isaac Sim and other UsdPhysics readers (usd-core's `pxr`).

Layout (metres, kilograms; the stage's upAxis is the part's up, see below):

    /<body>                 Xform, default prim; UsdPhysics RigidBodyAPI + MassAPI (mass, centre of
                            mass, principal inertia and the rotation to its principal axes)
      /splats               UsdVol.ParticleField3DGaussianSplat: the twin's Gaussians as fitted
                            (positions, unit orientations, linear scales, opacities after the
                            sigmoid, every SH coefficient of the fitted degree in 3DGS's basis and
                            order, DC first, `elementSize` (degree + 1)^2 per splat); purpose "render"
      /visual/<part>        one UsdGeom.Mesh per CAD part, named after it (made a valid identifier;
                            the CAD name is kept in customData "cad_part"), face colours baked from
                            the Gaussians; purpose "proxy" (the splats are the picture); no collision
      /collision/<shape>    the collision shapes of `collision.py`, invisible: convex pieces as Meshes
                            with CollisionAPI + MeshCollisionAPI approximation "convexHull"; primitives
                            as UsdGeom Cube / Sphere / Cylinder / Capsule with CollisionAPI

Up: the stage's upAxis is Y or Z, whichever is nearer the part's up in the object frame; when up is
not exactly that axis, the whole body (mesh, splats, collision, mass properties) is turned by the
smallest rotation that makes it so, and the layer's customLayerData records that rotation
(`cadsplat:stage_from_object`, 16 numbers, row-major [4, 4] acting on column vectors) and where up
came from (`cadsplat:up_source`, `cadsplat:up_detail`, `cadsplat:up_object`). A CAD model drawn Y-up or
Z-up keeps its object frame exactly.

The mass properties are written explicitly (not left to the importer to recompute from the
collision shapes, which would overstate the mass exactly as one convex hull does). The file is
written beside its destination, read back and checked (`check_usd`), then renamed into place.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

from calibration.fileio import fsync_dir
from calibration.so3 import matrix_to_quat
from reconstruction.gaussians import Gaussians
from reconstruction.splats import SH_C0
from simulation.collision import Primitive
from simulation.mjcf import BodySpec
from simulation.up import Up, standing, usd_up_axis


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


def turned_body(body: BodySpec, rotation: np.ndarray) -> BodySpec:
    """`body` turned about the object origin by rotation [3, 3]: its mesh, mass properties (centre of
    mass R c, inertia R I R^T) and collision shapes."""
    r = np.asarray(rotation, np.float64)
    a, m, col = body.asset, body.asset.mass, body.collision
    t = np.eye(4)
    t[:3, :3] = r
    mass = replace(m, center_of_mass=r @ m.center_of_mass, inertia=r @ m.inertia @ r.T)
    collision = replace(
        col,
        pieces=tuple(np.asarray(p) @ r.T for p in col.pieces),
        primitives=tuple(replace(p, transform=t @ p.transform) for p in col.primitives),
    )
    return replace(body, asset=replace(a, vertices=a.vertices @ r.T, mass=mass), collision=collision)


def stage_frame(up: Up) -> tuple[str, np.ndarray]:
    """(USD upAxis "Y" or "Z", rotation [3, 3] stage-from-object standing `up` along it)."""
    axis = usd_up_axis(up.vector)
    return axis, standing(up.vector, "+" + axis.lower())


def _splats(stage, path: str, g: Gaussians):
    """A ParticleField3DGaussianSplat prim at `path` holding `g` (see the module docstring)."""
    from pxr import Gf, UsdGeom, UsdVol, Vt

    means, quats, scales, opacity, sh = (t.numpy() for t in g.activated())
    q = quats / np.linalg.norm(quats, axis=1, keepdims=True)
    field = UsdVol.ParticleField3DGaussianSplat.Define(stage, path)
    field.CreatePositionsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(means, np.float32)))
    field.CreateOrientationsAttr(Vt.QuatfArray([Gf.Quatf(float(w), float(x), float(y), float(z)) for w, x, y, z in q]))
    field.CreateScalesAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(scales, np.float32)))
    field.CreateOpacitiesAttr(Vt.FloatArray.FromNumpy(np.ascontiguousarray(opacity, np.float32)))
    field.CreateRadianceSphericalHarmonicsDegreeAttr(int(g.sh_degree))
    coeffs = field.CreateRadianceSphericalHarmonicsCoefficientsAttr(
        Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(sh.reshape(-1, 3), np.float32))
    )
    primvar = UsdGeom.Primvar(coeffs)
    primvar.SetInterpolation(UsdGeom.Tokens.vertex)
    primvar.SetElementSize(int(sh.shape[1]))
    field.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, means.min(0))), Gf.Vec3f(*map(float, means.max(0)))]))
    rgb = np.clip(0.5 + SH_C0 * sh[:, 0], 0.0, 1.0)
    field.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex).Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(rgb, np.float32)))
    field.CreatePurposeAttr(UsdGeom.Tokens.render)
    return field


def usd_stage(body: BodySpec, splats: Gaussians | None = None, up_axis: str = "Z", layer_data: dict | None = None):
    """An in-memory Usd.Stage holding `body` and its `splats` (see the module docstring), already in
    the stage's frame, whose upAxis is `up_axis`; `layer_data` joins the layer's customLayerData."""
    import trimesh
    from pxr import Gf, Usd, UsdGeom, UsdPhysics, Vt

    a, col, m = body.asset, body.collision, body.asset.mass
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y if up_axis == "Y" else UsdGeom.Tokens.z)
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
    if splats is not None:
        _splats(stage, f"{root_path}/splats", splats)

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
        mesh.CreatePurposeAttr(UsdGeom.Tokens.proxy if splats is not None else UsdGeom.Tokens.default_)

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
    root.SetCustomDataByKey(
        "cadsplat:collision", {"kind": col.kind, "volume_error": float(col.volume_error), "hull_budget": int(col.hull_budget or 0)}
    )
    stage.GetRootLayer().customLayerData = {"generator": "cadsplat", **(layer_data or {})}
    return stage


def check_usd(path: str | os.PathLike, body: BodySpec, splats: Gaussians | None = None, up_axis: str = "Z") -> None:
    """Read `path` back with pxr and check it holds `body`: a rigid body with the mass, centre of
    mass and principal inertia of the asset, the asset's triangles, one collision prim per
    collision shape, the stage's up axis, `splats` through UsdVol's ParticleField3DGaussianSplat
    API (count, SH degree and coefficients, positions), and no error from OpenUSD's validators.
    Raises UsdCheckError naming the first mismatch."""
    from pxr import Usd, UsdGeom, UsdPhysics

    stage = Usd.Stage.Open(str(path))
    if stage is None:
        raise UsdCheckError(f"{path}: pxr cannot open the file just written")
    if (
        UsdGeom.GetStageUpAxis(stage) != up_axis
        or UsdGeom.GetStageMetersPerUnit(stage) != 1.0
        or UsdPhysics.GetStageKilogramsPerUnit(stage) != 1.0
    ):
        raise UsdCheckError(f"{path}: the stage's upAxis, metersPerUnit or kilogramsPerUnit is not what was written")
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
    if splats is not None:
        check_splats(path, root.GetChild("splats"), splats)
    errors = validation_errors(stage)
    if errors:
        raise UsdCheckError(f"{path}: OpenUSD's validators report {len(errors)} error(s), the first: {errors[0]}")


def validation_errors(stage) -> list[str]:
    """What OpenUSD's own validators (usdValidation: stage metadata, UsdPhysics rigid bodies and
    colliders, attribute types, composition, ...) report as errors on `stage`, one line each."""
    from pxr import UsdValidation

    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    found = UsdValidation.ValidationContext(validators).Validate(stage)
    return [f"{e.GetName()}: {e.GetMessage()}" for e in found if e.GetErrorType() == UsdValidation.ValidationErrorType.Error]


def check_splats(path, prim, splats: Gaussians) -> None:
    """`prim` read through UsdVol.ParticleField3DGaussianSplat holds `splats`; UsdCheckError otherwise."""
    from pxr import UsdGeom, UsdVol

    if not (prim and prim.IsA(UsdVol.ParticleField3DGaussianSplat)):
        raise UsdCheckError(f"{path}: no ParticleField3DGaussianSplat prim holds the splats")
    field = UsdVol.ParticleField3DGaussianSplat(prim)
    n, k = len(splats), splats.sh.shape[1]
    pos = np.array(field.GetPositionsAttr().Get(), np.float32)
    counts = [len(field.GetOrientationsAttr().Get()), len(field.GetScalesAttr().Get()), len(field.GetOpacitiesAttr().Get())]
    if pos.shape != (n, 3) or counts != [n, n, n]:
        raise UsdCheckError(
            f"{path}: the splat field holds {len(pos)} positions and {counts} orientations, scales, opacities; the twin has {n} splats"
        )
    if not np.allclose(pos, np.asarray(splats.means, np.float32), atol=1e-6):
        raise UsdCheckError(f"{path}: the splat positions differ from the twin's")
    coeffs = field.GetRadianceSphericalHarmonicsCoefficientsAttr()
    sh = np.array(coeffs.Get(), np.float32)
    if (
        field.GetRadianceSphericalHarmonicsDegreeAttr().Get() != splats.sh_degree
        or UsdGeom.Primvar(coeffs).GetElementSize() != k
        or sh.shape != (n * k, 3)
    ):
        raise UsdCheckError(
            f"{path}: the splats' SH degree or coefficient count is not the twin's (degree {splats.sh_degree}, {k} per splat)"
        )
    if not np.allclose(sh.reshape(n, k, 3), np.asarray(splats.sh, np.float32), atol=1e-6):
        raise UsdCheckError(f"{path}: the splats' SH coefficients differ from the twin's")


def _rigid(rotation: np.ndarray) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = rotation
    return t


def _canonical(tris: np.ndarray) -> np.ndarray:
    """Triangles [T, 3, 3] in an order-free form that keeps winding: each rolled to start at its
    lexicographically smallest corner, then the triangles sorted. Returns [T, 9]."""
    t = np.round(np.asarray(tris, np.float64), 9)
    first = [min(range(3), key=lambda i: tuple(tri[i])) for tri in t]
    keys = np.stack([np.roll(tri, -k, axis=0) for tri, k in zip(t, first)]).reshape(len(t), 9) if len(t) else t.reshape(0, 9)
    return keys[np.lexsort(keys.T[::-1])]


def write_usd(path: str | os.PathLike, body: BodySpec, splats: Gaussians | None = None, up: Up | None = None) -> Path:
    """Write `body` and its `splats` (object frame) standing on `up` (default: the object frame's +z)
    as a USD file (.usda text or .usd/.usdc binary) beside `path`, check it reads back as written
    (`check_usd`), then rename it into place. Returns `path`."""
    from pxr import Gf, Vt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    up = up or Up(np.array([0.0, 0.0, 1.0]), "default", "the CAD convention +z assumed")
    axis, rotation = stage_frame(up)
    stage_body = turned_body(body, rotation)
    stage_splats = None if splats is None else splats.transformed(_rigid(rotation))
    layer_data = {
        "cadsplat:up_source": up.source,
        "cadsplat:up_detail": up.detail,
        "cadsplat:up_object": Gf.Vec3d(*map(float, up.vector)),
        "cadsplat:stage_from_object": Vt.DoubleArray([float(x) for x in _rigid(rotation).reshape(-1)]),  # row-major, column vectors
    }
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        stage = usd_stage(stage_body, stage_splats, axis, layer_data)  # held: the layer lives only as long as its stage
        if not stage.GetRootLayer().Export(tmp):
            raise UsdCheckError(f"{path}: pxr could not write the file")
        check_usd(tmp, stage_body, stage_splats, axis)
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
        fsync_dir(path.parent)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path
