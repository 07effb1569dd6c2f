"""GLB of a twin's splats as a glTF `KHR_gaussian_splatting` primitive, with the deformed mesh alongside
when asked (Khronos, extensions/2.0/Khronos/KHR_gaussian_splatting).

The splat primitive is mode POINTS (0) with, per splat:

    POSITION                                    float VEC3, metres
    KHR_gaussian_splatting:ROTATION             float VEC4, unit quaternion, glTF order (x, y, z, w)
    KHR_gaussian_splatting:SCALE                float VEC3, linear (exp of the stored log-scales)
    KHR_gaussian_splatting:OPACITY              float SCALAR, after the sigmoid
    KHR_gaussian_splatting:SH_DEGREE_l_COEF_n   float VEC3, every coefficient of every degree fitted,
                                                3DGS's real SH basis and order (the extension's)
    COLOR_0                                     float VEC4, the fallback point colour: linear RGB of
                                                the diffuse colour, alpha = opacity

kernel "ellipse", colorSpace "srgb_rec709_display" (the splats were fitted to sRGB photographs).
Everything is written in glTF's frame, +Y up, the rotation from the object frame baked into the
data (positions, orientations and SH turned together), because the extension only recommends that
renderers turn SH with a node's rotation. The root node's `extras.cadsplat` records that rotation
(`gltf_from_object`, [4, 4]), where up came from, and the screen-space dilation the splats were fitted with
(`eps2d`, px^2), which the extension's kernel leaves out (a viewer adds it to draw them as trained).
"""

from __future__ import annotations

import json
import struct

import numpy as np

from reconstruction.gaussians import Gaussians
from reconstruction.mesh_io import MeshParts
from reconstruction.splats import SH_C0

EXTENSION = "KHR_gaussian_splatting"
FLOAT, UINT32 = 5126, 5125
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
POINTS, TRIANGLES = 0, 4
GLB_MAGIC, GLB_VERSION, CHUNK_JSON, CHUNK_BIN = 0x46546C67, 2, 0x4E4F534A, 0x004E4942


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear (IEC 61966-2-1)."""
    c = np.asarray(c, np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def sh_semantics(degree: int) -> list[str]:
    """The attribute names of every SH coefficient of degrees 0..degree, in coefficient order."""
    return [f"{EXTENSION}:SH_DEGREE_{level}_COEF_{n}" for level in range(degree + 1) for n in range(2 * level + 1)]


class _Builder:
    """Accumulates accessors, each in its own 4-byte aligned bufferView of one binary buffer."""

    def __init__(self) -> None:
        self.blob = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def add(self, data: np.ndarray, kind: str, target: int, *, bounds: bool = False) -> int:
        data = np.ascontiguousarray(data)
        component = UINT32 if data.dtype == np.uint32 else FLOAT
        offset = len(self.blob)
        self.blob += data.tobytes()
        self.blob += b"\0" * (-len(self.blob) % 4)
        self.views.append({"buffer": 0, "byteOffset": offset, "byteLength": data.nbytes, "target": target})
        acc = {"bufferView": len(self.views) - 1, "componentType": component, "count": int(data.shape[0]), "type": kind}
        if bounds:
            flat = data.reshape(data.shape[0], -1)
            acc["min"] = [float(x) for x in flat.min(0)]
            acc["max"] = [float(x) for x in flat.max(0)]
        self.accessors.append(acc)
        return len(self.accessors) - 1


def splat_attributes(b: _Builder, g: Gaussians) -> dict[str, int]:
    """The KHR_gaussian_splatting attributes (and COLOR_0) of `g`, added to `b`: name -> accessor."""
    means, quats, scales, opacity, sh = (t.numpy().astype(np.float64) for t in g.activated())
    q = quats / np.linalg.norm(quats, axis=1, keepdims=True)
    rgb = np.clip(0.5 + SH_C0 * sh[:, 0], 0.0, 1.0)
    attrs = {
        "POSITION": b.add(means.astype(np.float32), "VEC3", ARRAY_BUFFER, bounds=True),
        "COLOR_0": b.add(np.concatenate([srgb_to_linear(rgb), opacity[:, None]], 1).astype(np.float32), "VEC4", ARRAY_BUFFER),
        f"{EXTENSION}:ROTATION": b.add(q[:, [1, 2, 3, 0]].astype(np.float32), "VEC4", ARRAY_BUFFER),
        f"{EXTENSION}:SCALE": b.add(scales.astype(np.float32), "VEC3", ARRAY_BUFFER),
        f"{EXTENSION}:OPACITY": b.add(opacity.astype(np.float32), "SCALAR", ARRAY_BUFFER),
    }
    for k, name in enumerate(sh_semantics(g.sh_degree)):
        attrs[name] = b.add(sh[:, k].astype(np.float32), "VEC3", ARRAY_BUFFER)
    return attrs


def _mesh_primitives(b: _Builder, parts: MeshParts) -> list[tuple[str, dict]]:
    """(part name, TRIANGLES primitive with POSITION, NORMAL and indices) per non-empty part."""
    import trimesh

    out = []
    for p, name in enumerate(parts.part_names):
        sel = np.flatnonzero(parts.face_part == p)
        if sel.size == 0:
            continue
        used, local = np.unique(parts.faces[sel], return_inverse=True)
        mesh = trimesh.Trimesh(parts.vertices[used], local.reshape(-1, 3), process=False)
        normals = np.array(mesh.vertex_normals, np.float64)
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        # A vertex touched only by degenerate triangles has no normal; glTF wants unit ones all the same.
        normals = np.where(length > 1e-6, normals / np.maximum(length, 1e-12), np.array([0.0, 1.0, 0.0]))
        prim = {
            "attributes": {
                "POSITION": b.add(np.asarray(mesh.vertices, np.float32), "VEC3", ARRAY_BUFFER, bounds=True),
                "NORMAL": b.add(normals.astype(np.float32), "VEC3", ARRAY_BUFFER),
            },
            "indices": b.add(np.asarray(mesh.faces, np.uint32).reshape(-1), "SCALAR", ELEMENT_ARRAY_BUFFER),
            "mode": TRIANGLES,
            "material": 0,
        }
        out.append((str(name), prim))
    return out


def splats_gltf(g: Gaussians, mesh: MeshParts | None = None, *, name: str = "twin", extras: dict | None = None) -> tuple[dict, bytes]:
    """(glTF JSON document, binary buffer) of splats `g` and, when given, the mesh `mesh` (one node per
    part), both already in glTF's frame (+Y up, metres). `extras` goes to the root node's extras.cadsplat."""
    b = _Builder()
    meshes = [
        {
            "name": f"{name}_splats",
            "primitives": [
                {
                    "attributes": splat_attributes(b, g),
                    "mode": POINTS,
                    "extensions": {
                        EXTENSION: {
                            "kernel": "ellipse",
                            "colorSpace": "srgb_rec709_display",
                            "projection": "perspective",
                            "sortingMethod": "cameraDistance",
                        }
                    },
                }
            ],
        }
    ]
    nodes = [{"name": name, "children": []}, {"name": f"{name}_splats", "mesh": 0}]
    materials = []
    if mesh is not None:
        materials.append(
            {
                "name": "deformed_cad",
                "pbrMetallicRoughness": {"baseColorFactor": [0.6, 0.6, 0.6, 1.0], "metallicFactor": 0.0, "roughnessFactor": 0.8},
            }
        )
        for part, prim in _mesh_primitives(b, mesh):
            meshes.append({"name": part, "primitives": [prim]})
            nodes.append({"name": part, "mesh": len(meshes) - 1})
    nodes[0]["children"] = list(range(1, len(nodes)))
    if extras:
        nodes[0]["extras"] = {"cadsplat": extras}
    doc = {
        "asset": {"version": "2.0", "generator": "cadsplat"},
        "extensionsUsed": [EXTENSION],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": nodes,
        "meshes": meshes,
        "accessors": b.accessors,
        "bufferViews": b.views,
        "buffers": [{"byteLength": len(b.blob)}],
    }
    if materials:
        doc["materials"] = materials
    return doc, bytes(b.blob)


def glb_bytes(doc: dict, blob: bytes) -> bytes:
    """A binary glTF container (JSON chunk padded with spaces, BIN chunk with zeros, 4-byte aligned)."""
    js = json.dumps(doc, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    blob = blob + b"\0" * (-len(blob) % 4)
    total = 12 + 8 + len(js) + 8 + len(blob)
    return b"".join(
        [
            struct.pack("<III", GLB_MAGIC, GLB_VERSION, total),
            struct.pack("<II", len(js), CHUNK_JSON),
            js,
            struct.pack("<II", len(blob), CHUNK_BIN),
            blob,
        ]
    )


def read_glb(data: bytes) -> tuple[dict, bytes]:
    """(JSON document, BIN chunk) of a GLB; ValueError when it is not one."""
    if len(data) < 20:
        raise ValueError("not a GLB: too short")
    magic, version, total = struct.unpack_from("<III", data, 0)
    if magic != GLB_MAGIC or version != GLB_VERSION or total != len(data):
        raise ValueError("not a GLB 2.0 container")
    n, kind = struct.unpack_from("<II", data, 12)
    if kind != CHUNK_JSON:
        raise ValueError("a GLB whose first chunk is not JSON")
    doc = json.loads(data[20 : 20 + n])
    rest = 20 + n
    blob = b""
    if rest + 8 <= len(data):
        m, kind = struct.unpack_from("<II", data, rest)
        if kind == CHUNK_BIN:
            blob = data[rest + 8 : rest + 8 + m]
    return doc, blob


def accessor_array(doc: dict, blob: bytes, index: int) -> np.ndarray:
    """An accessor's elements [count, components] (float32 or uint32) of a GLB read by `read_glb`."""
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[acc["type"]]
    dtype = np.uint32 if acc["componentType"] == UINT32 else np.float32
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    return np.frombuffer(blob, dtype, acc["count"] * width, start).reshape(acc["count"], width)
