"""The twin format (SPEC "Twin"): a directory a simulator, a viewer and `cadsplat render` all read.

```
twin.json               model id, Sim(3) init + refined, per-camera camera-to-object poses, preset,
                        config (the whole resolved configuration), training (seed, views, what the
                        configuration was resolved from), choices (why, and what the run found),
                        timings_s, losses, versions
splats.ply              Inria 3DGS layout, deformed means, object frame (opens in 3DGS viewers);
                        SH padded with zeros to degree 3, the degree fitted in a `sh_degree` comment,
                        the screen-space dilation fitted (`eps2d`, also in twin.json) in an `eps2d` one

splats_canonical.npz    canonical means, face index, barycentrics, part label, part names
mesh_cad.glb            the retrieved CAD mesh (object frame, metres), one node per part, under a
                        root node that turns the z-up object frame into glTF's +Y up
mesh_deformed.glb       the CAD vertices moved by the field, same layout
renders/*.png           RGBA renders of the training views
manifest.json           sha256 of every file above (written last; `load_twin` verifies it)
```
The whole directory is written beside its destination and renamed into place, so a twin is
either complete or absent; an existing directory is only ever replaced when it holds a twin.
"""

from __future__ import annotations

import io
import json
import math
import os
import shutil
import tempfile
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from calibration.camera import Camera
from calibration.fileio import atomic_write_bytes, atomic_write_json, encode_png, fsync_dir, publish_dir
from calibration.guard import PathOutside, contained
from calibration.sim3 import Sim3
from reconstruction.gaussians import EPS2D_3DGS, Gaussians
from reconstruction.mesh_io import MeshParts, parts_glb_bytes, read_mesh_parts

TWIN_JSON = "twin.json"
SPLATS_PLY = "splats.ply"
CANONICAL_NPZ = "splats_canonical.npz"
MESH_CAD_GLB = "mesh_cad.glb"
MESH_DEFORMED_GLB = "mesh_deformed.glb"
MANIFEST_JSON = "manifest.json"
FORMAT_VERSION = 1


class TwinError(ValueError):
    """A twin directory that cannot be read as it is; the message names the file and the problem."""


@dataclass(frozen=True)
class TwinCamera:
    """One training view of a twin: its image, intrinsics and the refined camera-to-object pose (OpenCV)."""

    file_path: str
    camera_id: str
    K: np.ndarray
    width: int
    height: int
    c2w_object_opencv: np.ndarray

    @property
    def camera(self) -> Camera:
        return Camera(self.K, self.width, self.height, np.zeros(0), self.c2w_object_opencv)

    def to_dict(self) -> dict:
        return {
            "file_path": self.file_path,
            "camera_id": self.camera_id,
            "K": np.asarray(self.K).tolist(),
            "width": int(self.width),
            "height": int(self.height),
            "c2w_object_opencv": np.asarray(self.c2w_object_opencv).tolist(),
        }

    @staticmethod
    def from_dict(d: dict) -> TwinCamera:
        return TwinCamera(
            d["file_path"],
            str(d.get("camera_id", Path(d["file_path"]).stem)),
            np.array(d["K"], np.float64),
            int(d["width"]),
            int(d["height"]),
            np.array(d["c2w_object_opencv"], np.float64),
        )


@dataclass
class Twin:
    """A reconstructed, CAD-registered twin: its `gaussians` (deformed, object frame, metres) and
    where each sits on the CAD surface: means_canonical [N, 3] float32, face_index [N] int (-1 when
    not anchored), barycentrics [N, 3] float32, part_label [N] int indexing part_names.
    """

    model_id: str
    sim3_rig_to_object_init: Sim3
    sim3_rig_to_object: Sim3
    cameras: list[TwinCamera]
    preset: str
    choices: dict
    timings_s: dict
    losses: dict
    gaussians: Gaussians
    means_canonical: np.ndarray
    face_index: np.ndarray
    barycentrics: np.ndarray
    part_label: np.ndarray
    part_names: list[str]
    pose_mode: str = "global"
    versions: dict = field(default_factory=dict)
    config: dict = field(default_factory=dict)  # the whole resolved configuration (`presets.Preset.to_dict`)
    training: dict = field(default_factory=dict)  # seed, training views (capture indices), what the configuration was resolved from
    root: Path | None = None
    up_object: dict | None = None  # {"vector": [3] unit, object frame, away from gravity; "source", "detail": what it was measured from}

    def __post_init__(self) -> None:
        g = self.gaussians
        self.gaussians = Gaussians.from_arrays(g.means, g.quats, g.log_scales, g.opacity_logits, g.sh, g.eps2d)
        n = len(self.gaussians)
        shapes = {
            "means_canonical": (self.means_canonical, (n, 3)),
            "face_index": (self.face_index, (n,)),
            "barycentrics": (self.barycentrics, (n, 3)),
            "part_label": (self.part_label, (n,)),
        }
        for name, (arr, shape) in shapes.items():
            if np.shape(arr) != shape:
                raise TwinError(f"twin {name} has shape {np.shape(arr)}, expected {shape}")
        arrays = {name: getattr(self.gaussians, name) for name in ("means", "quats", "log_scales", "opacity_logits", "sh")}
        for name in ("means_canonical", "barycentrics"):
            arrays[name] = np.asarray(getattr(self, name), np.float32)
            setattr(self, name, arrays[name])
        for name, arr in arrays.items():
            if not np.all(np.isfinite(arr)):
                raise TwinError(f"twin {name} contains NaN or inf")
        for name in ("face_index", "part_label"):
            setattr(self, name, np.asarray(getattr(self, name), np.int64))
        if n and (self.part_label.min() < 0 or self.part_label.max() >= len(self.part_names)):
            raise TwinError("twin part_label indexes outside part_names")

    @property
    def num_splats(self) -> int:
        return len(self.gaussians)

    @property
    def mesh_deformed_path(self) -> Path | None:
        return None if self.root is None else self.root / MESH_DEFORMED_GLB

    @property
    def mesh_cad_path(self) -> Path | None:
        return None if self.root is None else self.root / MESH_CAD_GLB

    def load_mesh_cad(self) -> MeshParts:
        return read_mesh_parts(self._need(MESH_CAD_GLB))

    def load_mesh_deformed(self) -> MeshParts:
        return read_mesh_parts(self._need(MESH_DEFORMED_GLB))

    def _need(self, name: str) -> Path:
        if self.root is None or not (self.root / name).exists():
            raise TwinError(f"twin has no {name} (it was never saved, or the file is missing)")
        return self.root / name


# ---------------------------------------------------------------------------------------- PLY


def ply_columns(sh_degree: int) -> list[str]:
    """Column names of the Inria 3DGS PLY for `sh_degree`, in file order."""
    k = (sh_degree + 1) ** 2
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(3 * (k - 1))]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


# Inria's loader (and most viewers built on it) reads exactly 3 * ((D + 1)^2 - 1) f_rest columns for
# its configured degree D, 3 unless a flag says otherwise, and no header field. So files are written
# at degree 3 with the missing bands zero, which renders identically; the degree actually fitted is
# kept in a `sh_degree N` header comment, which `read_splats_ply` uses to drop the padding again.
PLY_SH_DEGREE = 3
PLY_DEGREE_COMMENT = "sh_degree"
# The screen-space dilation the splats were fitted with (`Gaussians.eps2d`), which Inria-layout viewers do not read
# (they draw with 3DGS's 0.3): an `eps2d V` header comment keeps it for readers that do.
PLY_EPS2D_COMMENT = "eps2d"


def splats_to_ply_bytes(gaussians: Gaussians) -> bytes:
    """Binary little-endian PLY in the Inria 3DGS layout, SH zero-padded to PLY_SH_DEGREE, normals the
    splats' disk normals.

    f_rest is channel-major as Inria writes it: all R coefficients of degrees >= 1, then G, then B.
    """
    from plyfile import PlyData, PlyElement

    g = gaussians
    n, degree = len(g), g.sh_degree
    written = max(degree, PLY_SH_DEGREE)
    padded = np.asarray(g.with_sh_degree(written).sh, np.float32)
    rest = padded[:, 1:, :].transpose(0, 2, 1).reshape(n, -1)
    cols = np.concatenate(
        [
            g.means,
            splat_normals(np.asarray(g.quats)),
            padded[:, 0, :],
            rest,
            np.asarray(g.opacity_logits).reshape(n, 1),
            g.log_scales,
            g.quats,
        ],
        1,
    ).astype(np.float32)
    names = ply_columns(written)
    rec = np.empty(n, dtype=[(c, "f4") for c in names])
    for i, c in enumerate(names):
        rec[c] = cols[:, i]
    buf = io.BytesIO()
    comments = [f"{PLY_DEGREE_COMMENT} {degree}", f"{PLY_EPS2D_COMMENT} {g.eps2d!r}"]
    PlyData([PlyElement.describe(rec, "vertex")], byte_order="<", comments=comments).write(buf)
    return buf.getvalue()


def read_splats_ply(path: str | os.PathLike) -> Gaussians:
    """The Gaussians of an Inria-layout 3DGS PLY (its normal columns are not read: they follow from the quats).

    The degree is the file's `sh_degree` comment when it has one and the bands above it are zero
    (padding), else the one its f_rest columns make; the dilation is its `eps2d` comment, else 3DGS's.
    """
    from plyfile import PlyData

    try:
        ply = PlyData.read(str(path))
        v = ply["vertex"]
    except Exception as e:  # noqa: BLE001 - plyfile raises its own parse errors (not ValueError) on a truncated file
        raise TwinError(f"{path}: not a readable 3DGS PLY ({type(e).__name__}: {e})") from None
    names = [p.name for p in v.properties]
    n_rest = sum(1 for c in names if c.startswith("f_rest_"))
    k = 1 + n_rest // 3
    degree = int(round(np.sqrt(k))) - 1
    if (degree + 1) ** 2 != k or 3 * (k - 1) != n_rest:
        raise TwinError(f"{path}: {n_rest} f_rest columns do not form a whole SH degree")
    missing = [c for c in ply_columns(degree) if c not in names]
    if missing:
        raise TwinError(f"{path}: missing 3DGS columns {', '.join(missing[:4])}")
    declared = [int(w[1]) for w in (c.split() for c in ply.comments) if len(w) == 2 and w[0] == PLY_DEGREE_COMMENT and w[1].isdigit()]
    eps2d = [w[1] for w in (c.split() for c in ply.comments) if len(w) == 2 and w[0] == PLY_EPS2D_COMMENT]

    def cols(*cs):
        return np.stack([np.asarray(v[c], np.float32) for c in cs], 1)

    n = len(v["x"])
    sh = np.zeros((n, k, 3), np.float32)
    sh[:, 0] = cols("f_dc_0", "f_dc_1", "f_dc_2")
    if k > 1:
        sh[:, 1:] = cols(*[f"f_rest_{i}" for i in range(n_rest)]).reshape(n, 3, k - 1).transpose(0, 2, 1)
    if declared and declared[0] < degree and not sh[:, (declared[0] + 1) ** 2 :].any():  # only padding is dropped
        degree = declared[0]
        sh = np.ascontiguousarray(sh[:, : (degree + 1) ** 2])
    return Gaussians(
        means=cols("x", "y", "z"),
        quats=cols("rot_0", "rot_1", "rot_2", "rot_3"),
        log_scales=cols("scale_0", "scale_1", "scale_2"),
        opacity_logits=np.asarray(v["opacity"], np.float32),
        sh=sh,
        eps2d=_eps2d(_comment_number(eps2d[0]) if eps2d else EPS2D_3DGS, f"{path}: its {PLY_EPS2D_COMMENT} comment"),
    )


def _eps2d(value, where: str) -> float:
    """A stored dilation (a JSON number) as a float, or one TwinError naming `where`."""
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    if not (number and math.isfinite(value) and value >= 0.0):
        raise TwinError(f"{where} must be a screen-space variance >= 0 px^2, got {value!r}")
    return float(value)


def _comment_number(text: str) -> float | str:
    """A PLY comment's word as a float, or the word itself when it is not one (for the error message)."""
    try:
        return float(text)
    except ValueError:
        return text


# ---------------------------------------------------------------------------------------- twin dir


def _twin_document(twin: Twin) -> dict:
    return {
        "format": "cadsplat-twin",
        "format_version": FORMAT_VERSION,
        "model_id": twin.model_id,
        "sim3_rig_to_object_init": twin.sim3_rig_to_object_init.to_dict(),
        "sim3_rig_to_object": twin.sim3_rig_to_object.to_dict(),
        "pose_mode": twin.pose_mode,
        "cameras": [c.to_dict() for c in twin.cameras],
        "num_splats": twin.num_splats,
        "sh_degree": twin.gaussians.sh_degree,
        "eps2d": twin.gaussians.eps2d,
        "part_names": list(twin.part_names),
        "preset": twin.preset,
        "config": twin.config,
        "training": twin.training,
        "choices": twin.choices,
        "timings_s": twin.timings_s,
        "losses": twin.losses,
        "versions": twin.versions,
        **({"up_object": twin.up_object} if twin.up_object is not None else {}),
    }


def object_up(up_rig: dict, sim3_rig_to_object: Sim3) -> dict:
    """A capture's rig-frame up (`up_rig`: {"vector" [3], "source", "detail"}, as its calibration measured it) in the
    object frame of `sim3_rig_to_object`'s registration: the record `Twin.up_object` keeps, source and detail kept."""
    v = sim3_rig_to_object.rotation @ np.asarray(up_rig["vector"], np.float64)
    detail = up_rig.get("detail", "the capture's up_rig")
    return {
        "vector": [float(x) for x in v / np.linalg.norm(v)],
        "source": str(up_rig.get("source", "calibration")),
        "detail": f"{detail}, through the twin's registration",
    }


def splat_normals(quats: np.ndarray) -> np.ndarray:
    """Local z axis of each splat (the disk normal) [N, 3] from quats [N, 4] wxyz."""
    q = quats / np.maximum(np.linalg.norm(quats, axis=1, keepdims=True), 1e-12)
    w, x, y, z = q.T
    return np.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], 1).astype(np.float32)


def save_twin(
    twin: Twin,
    out_dir: str | os.PathLike,
    *,
    mesh_cad: MeshParts | None = None,
    mesh_deformed: MeshParts | None = None,
    renders: dict[str, np.ndarray] | None = None,
    overwrite: bool = False,
) -> Path:
    """Write `twin` as a directory, atomically (built beside `out_dir`, then renamed into place).

    renders: image name -> RGBA float [H, W, 4]. An existing `out_dir` is replaced only with `overwrite`.
    Returns `out_dir`; `twin.root` points there afterwards.
    """
    out = Path(out_dir)
    check_replaceable(out, overwrite)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".incoming", dir=out.parent))
    try:
        digests = {}
        digests[SPLATS_PLY] = atomic_write_bytes(
            tmp / SPLATS_PLY,
            splats_to_ply_bytes(twin.gaussians),
        )
        buf = io.BytesIO()
        np.savez_compressed(
            buf,
            means_canonical=twin.means_canonical,
            face_index=twin.face_index,
            barycentrics=twin.barycentrics,
            part_label=twin.part_label,
            part_names=np.array(twin.part_names, dtype=str),
        )
        digests[CANONICAL_NPZ] = atomic_write_bytes(tmp / CANONICAL_NPZ, buf.getvalue())
        if mesh_cad is not None:
            digests[MESH_CAD_GLB] = atomic_write_bytes(tmp / MESH_CAD_GLB, parts_glb_bytes(mesh_cad))
        if mesh_deformed is not None:
            digests[MESH_DEFORMED_GLB] = atomic_write_bytes(tmp / MESH_DEFORMED_GLB, parts_glb_bytes(mesh_deformed))
        if renders:
            (tmp / "renders").mkdir()
            for name, rgba in renders.items():
                rel = f"renders/{Path(name).stem}.png"
                digests[rel] = atomic_write_bytes(tmp / rel, encode_png(rgba))
            fsync_dir(tmp / "renders")
        digests[TWIN_JSON] = atomic_write_json(tmp / TWIN_JSON, _twin_document(twin))
        atomic_write_json(tmp / MANIFEST_JSON, {"format": "cadsplat-twin-manifest", "sha256": digests})
        fsync_dir(tmp)
        publish_dir(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    twin.root = out
    return out


def is_twin_dir(path: str | os.PathLike) -> bool:
    """True when `path` is a directory whose twin.json says it is a cadsplat twin (damaged or not)."""
    try:
        return json.loads((Path(path) / TWIN_JSON).read_text()).get("format") == "cadsplat-twin"
    except (OSError, ValueError, AttributeError):
        return False


def check_replaceable(out: Path, overwrite: bool) -> None:
    """Raise TwinError unless `out` is free, or holds a twin and `overwrite` allows replacing it."""
    if not out.exists():
        return
    if not overwrite:
        raise TwinError(f"{out}: already exists; pass overwrite to replace the twin")
    if not is_twin_dir(out):
        raise TwinError(f"{out}: is not a twin directory (no cadsplat twin.json), so it is not replaced; choose another output")


def verify_twin(root: Path) -> None:
    """Check every file against manifest.json (twins written before manifests have none: nothing to check)."""
    path = root / MANIFEST_JSON
    if not path.exists():
        return
    from calibration.fileio import sha256_file

    try:
        digests = json.loads(path.read_text())["sha256"]
        items = sorted(digests.items())
    except (ValueError, KeyError, TypeError, AttributeError):
        raise TwinError(f"{path}: not a readable twin manifest") from None
    for rel, digest in items:
        try:
            file = contained(root, rel, what=f"{MANIFEST_JSON} entry")
        except PathOutside as e:
            raise TwinError(f"{path}: {e}") from None
        if not file.is_file():
            raise TwinError(f"{root / rel}: listed in {MANIFEST_JSON} but missing")
        if sha256_file(file) != digest:
            raise TwinError(f"{root / rel}: sha256 does not match {MANIFEST_JSON} (file changed or corrupt)")


def load_twin(path: str | os.PathLike, *, verify: bool = True) -> Twin:
    """Read a twin directory written by `save_twin`, every file checked against its manifest by default."""
    root = Path(path)
    doc_path = root / TWIN_JSON
    if not doc_path.exists():
        raise TwinError(f"{root}: no {TWIN_JSON} here; is this a twin directory?")
    try:
        doc = json.loads(doc_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise TwinError(f"{doc_path}: invalid JSON ({getattr(e, 'msg', e)})") from None
    if not isinstance(doc, dict) or doc.get("format") != "cadsplat-twin":
        raise TwinError(f"{doc_path}: not a cadsplat twin document")
    if verify:
        verify_twin(root)
    for name in (SPLATS_PLY, CANONICAL_NPZ):
        if not (root / name).exists():
            raise TwinError(f"{root / name}: file is missing")
    ply = read_splats_ply(root / SPLATS_PLY)
    try:
        with np.load(root / CANONICAL_NPZ) as z:
            canon = {k: z[k] for k in z.files}
        canon = {k: canon[k] for k in ("means_canonical", "face_index", "barycentrics", "part_label", "part_names")}
    except Exception as e:  # noqa: BLE001 - numpy/zipfile raise many types on a damaged archive
        raise TwinError(f"{root / CANONICAL_NPZ}: not a readable splat archive ({type(e).__name__})") from None
    try:
        return _twin_from(doc, ply, canon, root)
    except (KeyError, TypeError, ValueError) as e:
        raise TwinError(f"{doc_path}: a field is missing or malformed ({e})") from None


def _twin_from(doc: dict, ply: Gaussians, canon: dict, root: Path) -> Twin:
    return Twin(
        model_id=doc["model_id"],
        sim3_rig_to_object_init=Sim3.from_dict(doc["sim3_rig_to_object_init"]),
        sim3_rig_to_object=Sim3.from_dict(doc["sim3_rig_to_object"]),
        cameras=[TwinCamera.from_dict(c) for c in doc["cameras"]],
        preset=doc.get("preset", ""),
        choices=doc.get("choices", {}),
        timings_s=doc.get("timings_s", {}),
        losses=doc.get("losses", {}),
        # Twins written before the field existed were all fitted with 3DGS's dilation.
        gaussians=replace(ply, eps2d=_eps2d(doc.get("eps2d", EPS2D_3DGS), "twin.json's eps2d")),
        means_canonical=canon["means_canonical"],
        face_index=canon["face_index"],
        barycentrics=canon["barycentrics"],
        part_label=canon["part_label"],
        part_names=[str(s) for s in canon["part_names"]],
        pose_mode=doc.get("pose_mode", "global"),
        versions=doc.get("versions", {}),
        config=doc.get("config", {}),
        training=doc.get("training", {}),
        root=root,
        up_object=doc.get("up_object"),
    )


def software_versions() -> dict:
    """Versions recorded in twin.json so a twin can be traced to the code that made it."""
    from importlib.metadata import PackageNotFoundError, version

    out = {"format": FORMAT_VERSION}
    for pkg in ("cadsplat", "torch", "numpy"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = "unknown"
    return out
