"""The .spz writer against a reader written here from Niantic's format description (README "File
Format", legacy gzip layout, version 3), not from the writer: every attribute comes back within its
quantisation step."""

from __future__ import annotations

import gzip
import struct

import numpy as np
import pytest

from reconstruction.gaussians import Gaussians
from reconstruction.twin import splats_to_ply_bytes
from simulation.spz import spz_bytes


def read_spz(data: bytes) -> dict:
    """Niantic's layout: gzip( header(magic, version, numPoints, shDegree, fractionalBits, flags, reserved),
    positions 24-bit fixed, alphas u8, colors u8, scales u8, rotations (v3: u32 smallest-three), sh u8 )."""
    raw = gzip.decompress(data)
    magic, version, n, degree, frac, flags, reserved = struct.unpack_from("<IIIBBBB", raw, 0)
    assert magic == 0x5053474E and raw[:4] == b"NGSP" and version == 3 and reserved == 0
    off = 16
    pos = np.frombuffer(raw, np.uint8, n * 9, off).reshape(n, 3, 3).astype(np.int32)
    off += n * 9
    fixed = pos[..., 0] | (pos[..., 1] << 8) | (pos[..., 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    alpha = np.frombuffer(raw, np.uint8, n, off).astype(np.float64)
    off += n
    color = np.frombuffer(raw, np.uint8, n * 3, off).reshape(n, 3).astype(np.float64)
    off += n * 3
    scale = np.frombuffer(raw, np.uint8, n * 3, off).reshape(n, 3).astype(np.float64)
    off += n * 3
    comp = np.frombuffer(raw, "<u4", n, off).astype(np.int64)
    off += n * 4
    k = (degree + 1) ** 2 - 1
    sh = np.frombuffer(raw, np.uint8, n * k * 3, off).reshape(n, k, 3).astype(np.float64)
    off += n * k * 3
    assert off == len(raw)
    quats = np.zeros((n, 4))  # x, y, z, w
    largest = comp >> 30
    rest = comp.copy()
    total = np.zeros(n)
    for i in (3, 2, 1, 0):  # the last-packed component sits in the lowest bits
        skip = largest == i
        mag = (rest & 511) / 511.0 * np.sqrt(0.5)
        val = np.where((rest >> 9) & 1, -mag, mag)
        quats[:, i] = np.where(skip, 0.0, val)
        total += np.where(skip, 0.0, val * val)
        rest = np.where(skip, rest, rest >> 10)
    quats[np.arange(n), largest] = np.sqrt(np.maximum(1.0 - total, 0.0))
    return {
        "degree": degree,
        "flags": flags,
        "means": fixed / float(1 << frac),
        "opacity": alpha / 255.0,
        "dc": (color / 255.0 - 0.5) / 0.15,
        "log_scales": scale / 16.0 - 10.0,
        "quats_wxyz": quats[:, [3, 0, 1, 2]],
        "sh_rest": (sh - 128.0) / 128.0,
    }


def gaussians(n: int = 400, degree: int = 2, seed: int = 0) -> Gaussians:
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2
    sh = rng.normal(0, 0.3, (n, k, 3))
    sh[:, 0] = rng.normal(0, 1.0, (n, 3))
    return Gaussians.from_arrays(
        rng.uniform(-0.2, 0.2, (n, 3)), rng.normal(size=(n, 4)), rng.uniform(-7, -3, (n, 3)), rng.normal(0, 2, n), sh
    )


def test_every_attribute_reads_back_within_its_quantisation_step():
    g = gaussians()
    got = read_spz(spz_bytes(g))
    assert got["degree"] == 2 and got["flags"] == 0 and len(got["means"]) == len(g)
    np.testing.assert_allclose(got["means"], g.means, atol=0.5 / 4096 + 1e-7)
    np.testing.assert_allclose(got["opacity"], 1 / (1 + np.exp(-g.opacity_logits.astype(np.float64))), atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(got["dc"], np.clip(g.sh[:, 0], -0.5 / 0.15, 0.5 / 0.15), atol=0.5 / (255 * 0.15) + 1e-5)
    np.testing.assert_allclose(got["log_scales"], g.log_scales, atol=0.5 / 16 + 1e-6)
    q = g.quats / np.linalg.norm(g.quats, axis=1, keepdims=True)
    angle = np.degrees(2 * np.arccos(np.clip(np.abs((got["quats_wxyz"] * q).sum(1)), 0, 1)))
    assert angle.max() < 0.3  # the same rotation (q and -q alike) to 9 bits a component
    rest = np.clip(g.sh[:, 1:], -1, 127 / 128)
    np.testing.assert_allclose(got["sh_rest"][:, :3], rest[:, :3], atol=4.5 / 128)  # degree 1: 5 bits, buckets of 8/128
    np.testing.assert_allclose(got["sh_rest"][:, 3:], rest[:, 3:], atol=8.5 / 128)  # degree 2: 4 bits, buckets of 16/128


def test_degree_zero_has_no_sh_block_and_the_file_is_far_smaller_than_the_ply():
    g = gaussians(n=3000, degree=0)
    data = spz_bytes(g)
    assert read_spz(data)["degree"] == 0
    assert len(data) * 5 < len(splats_to_ply_bytes(g))


def test_positions_beyond_the_fixed_point_range_are_refused():
    g = gaussians(n=2, degree=0)
    far = Gaussians.from_arrays(g.means + 3000.0, g.quats, g.log_scales, g.opacity_logits, g.sh)
    with pytest.raises(ValueError, match="24-bit"):
        spz_bytes(far)


def test_the_file_read_back_renders_as_the_splats_do():
    """Quantised as the format is, the splats read back draw the same picture: PSNR over 35 dB."""
    from calibration.camera import look_at_c2w
    from reconstruction.gaussians import render

    rng = np.random.default_rng(2)
    n = 500
    sh = rng.normal(0, 0.25, (n, 4, 3))
    g = Gaussians.from_arrays(rng.normal(0, 0.03, (n, 3)), rng.normal(size=(n, 4)), rng.uniform(-5.5, -4, (n, 3)), rng.normal(1, 1, n), sh)
    r = read_spz(spz_bytes(g))
    opacity = np.clip(r["opacity"], 1e-6, 1 - 1e-6)
    back = Gaussians.from_arrays(
        r["means"], r["quats_wxyz"], r["log_scales"], np.log(opacity / (1 - opacity)), np.concatenate([r["dc"][:, None], r["sh_rest"]], 1)
    )
    k = np.array([[150.0, 0, 64], [0, 150.0, 48], [0, 0, 1]])
    viewmat = np.linalg.inv(look_at_c2w(np.array([0.2, 0.15, 0.1]), np.zeros(3)))
    want, _ = render(g, viewmat[None], k[None], 128, 96)
    got, _ = render(back, viewmat[None], k[None], 128, 96)
    mse = float(((got - want) ** 2).mean())
    assert 10 * np.log10(1.0 / mse) > 35
