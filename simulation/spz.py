"""Niantic's `.spz` (MIT): a twin's splats about ten times smaller than the PLY, in the legacy gzip
layout (version 3) that the web loaders (Spark, Babylon.js, PlayCanvas) and Niantic's own library read.

One gzip stream holding a 16-byte header and the attributes one after another, all little-endian:

    header      magic 0x5053474e ("NGSP"), version 3, numPoints (uint32), shDegree, fractionalBits,
                flags, reserved (uint8 each)
    positions   [N, 3] 24-bit signed fixed point with `fractionalBits` fractional bits
    alphas      [N]    uint8, opacity after the sigmoid times 255
    colors      [N, 3] uint8, the DC SH coefficient times 0.15 * 255, plus 127.5
    scales      [N, 3] uint8, (log-scale + 10) * 16
    rotations   [N]    uint32, "smallest three": the index of the largest |component| (x, y, z, w order)
                       in the top 2 bits, then for each other component a sign bit and 9 bits of
                       |c| / sqrt(1/2), the largest made positive
    sh          [N, K - 1, 3] int8 + 128, coefficient-major with colour inner (3DGS's basis and order),
                       value * 128 rounded to 5 bits for degree 1 and 4 bits above, as Niantic packs them

The data are stored in spz's RUB frame (x right, y up, z back), which is glTF's: callers pass the
splats already turned into it (`simulation.up`). The file has no room for metadata; the export's
manifest records the rotation and where up came from.
"""

from __future__ import annotations

import gzip
import struct

import numpy as np

from reconstruction.gaussians import Gaussians

MAGIC = 0x5053474E
VERSION = 3
FRACTIONAL_BITS = 12  # Niantic's packer's choice: 0.24 mm steps, +-2 km of range
COLOR_SCALE = 0.15
SH1_BUCKET, SH_REST_BUCKET = 1 << (8 - 5), 1 << (8 - 4)


def _to_uint8(x: np.ndarray) -> np.ndarray:
    """Round half away from zero and clamp to [0, 255], as the reference packer's toUint8."""
    x = np.asarray(x, np.float64)
    return np.clip(np.sign(x) * np.floor(np.abs(x) + 0.5), 0, 255).astype(np.uint8)


def pack_positions(means: np.ndarray, fractional_bits: int = FRACTIONAL_BITS) -> np.ndarray:
    """means [N, 3] metres -> [N * 9] bytes of 24-bit little-endian fixed point."""
    fixed = np.round(np.asarray(means, np.float64) * (1 << fractional_bits)).astype(np.int64)
    if np.abs(fixed).max(initial=0) >= 1 << 23:
        raise ValueError(f"splat positions beyond +-{(1 << 23) / (1 << fractional_bits):g} m do not fit spz's 24-bit fixed point")
    u = fixed.reshape(-1) & 0xFFFFFF
    return np.stack([u & 0xFF, (u >> 8) & 0xFF, (u >> 16) & 0xFF], 1).astype(np.uint8).reshape(-1)


def pack_rotations(quats_wxyz: np.ndarray) -> np.ndarray:
    """quats [N, 4] wxyz (any norm) -> [N] uint32, smallest-three with 9-bit magnitudes."""
    q = np.asarray(quats_wxyz, np.float64)[:, [1, 2, 3, 0]]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    largest = np.argmax(np.abs(q), axis=1)
    negate = q[np.arange(len(q)), largest] < 0
    comp = largest.astype(np.uint64)
    for i in range(4):
        neg = ((q[:, i] < 0) ^ negate).astype(np.uint64)
        mag = np.floor(511.0 * np.abs(q[:, i]) / np.sqrt(0.5) + 0.5).astype(np.uint64)
        packed = (comp << np.uint64(10)) | (neg << np.uint64(9)) | mag
        comp = np.where(largest == i, comp, packed)
    return comp.astype(np.uint32)


def quantize_sh(x: np.ndarray, bucket: int) -> np.ndarray:
    """SH values -> uint8 (value * 128 + 128) rounded to the centre of `bucket`-wide steps."""
    q = np.round(np.asarray(x, np.float64) * 128.0).astype(np.int64) + 128
    q = (q + bucket // 2) // bucket * bucket
    return np.clip(q, 0, 255).astype(np.uint8)


def spz_bytes(g: Gaussians) -> bytes:
    """The gzip-compressed .spz (version 3) of the splats `g` (already in the RUB frame)."""
    means, quats = np.asarray(g.means, np.float64), np.asarray(g.quats, np.float64)
    n, degree = len(g), g.sh_degree
    sh = np.asarray(g.sh, np.float64)
    opacity = 1.0 / (1.0 + np.exp(-np.asarray(g.opacity_logits, np.float64)))
    rest = sh[:, 1:, :]
    sh_bytes = (
        np.concatenate([quantize_sh(rest[:, :3], SH1_BUCKET), quantize_sh(rest[:, 3:], SH_REST_BUCKET)], 1)
        if degree
        else np.zeros((n, 0, 3), np.uint8)
    )
    body = b"".join(
        [
            struct.pack("<IIIBBBB", MAGIC, VERSION, n, degree, FRACTIONAL_BITS, 0, 0),
            pack_positions(means).tobytes(),
            _to_uint8(opacity * 255.0).tobytes(),
            _to_uint8(sh[:, 0] * (COLOR_SCALE * 255.0) + 0.5 * 255.0).tobytes(),
            _to_uint8((np.asarray(g.log_scales, np.float64) + 10.0) * 16.0).tobytes(),
            pack_rotations(quats).astype("<u4").tobytes(),
            sh_bytes.tobytes(),
        ]
    )
    return gzip.compress(body, compresslevel=9, mtime=0)
