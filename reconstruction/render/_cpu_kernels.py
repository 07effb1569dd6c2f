"""Numba CPU kernels of the rasterizer: projection, tile binning, compositing and their VJPs.

Why numba: the same forward compositing kernel ported to C++ (g++ -O3 -march=native, same data
layout) ran level with this one (benchmarks/results/rasterizer.md), so a C++ torch extension would buy no speed
for a compiler at install time and a build in CI; NVIDIA Warp runs CPU kernels on one thread with no SIMD
(NVIDIA/warp#1309). numba's `cache=True` keeps the one-off compile of all kernels out of every later process.

Every float array is float64 (callers cast), except the rendered images the compositing kernels hand
back and their gradients, which are in the caller's dtype: a float32 pixel-space mean near x = 500 px
is off by up to 3e-5 px, which alone moves a sharp splat's alpha by more than the 1e-5 the rasterizer
promises.
Kernels take numpy arrays and write into preallocated outputs. Those that run in parallel take a
leading (lo, hi) range of their parallel index and are driven by `reconstruction.parallel.parallel_for`; they write
disjoint outputs per index, and sums run over fixed chunks (of Gaussians) or per slot, so results
are bit-identical whatever the thread count.

Conventions shared by all kernels:
- conic (a, b, c) is the inverse 2D covariance [[a, b], [b, c]]; sigma = 0.5 (a dx^2 + c dy^2) + b dx dy
  with (dx, dy) = pixel centre - mean2d.
- A Gaussian is visible in a camera iff its radius_x > 0 (projection culls with both radii zero).
- rects [C * N, 4] are inclusive pixel ranges (u_lo, u_hi, v_lo, v_hi) of the pixel centres inside the
  bounding box of the alpha >= 1/255 ellipse, clipped to the image; tiles follow as pixel // tile_size.
- A "slot" is one (camera, Gaussian, tile) intersection. Slots are numbered k in tile order (each
  tile's slots front to back, `tile_offsets` delimiting the tiles) and carry their own float64 record
  (SF_* columns), int32 record (SI_* columns) and colour row, so compositing reads a tile's splats
  from consecutive memory. `slot_at` lists the slots pair-major: pair cg = c * N + g owns
  slot_at[slot_offsets[cg]:slot_offsets[cg + 1]], one per tile of its tile rectangle in row-major
  order. Kernels that run per tile write per-slot partial results and a per-pair pass sums them in
  that order, which needs no atomics.
"""

from __future__ import annotations

import math

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

ALPHA_THRESHOLD = 1.0 / 255.0
ALPHA_MAX = 0.999
TRANSMITTANCE_MIN = 1e-4
# Pixels are listed when sigma <= ln(255 opacity) + this margin, far above the rounding of either
# side, so the per-pixel alpha test (not the listing) decides every borderline pixel.
_SIGMA_MARGIN = 1e-9
# Relative and absolute widening of the closed-form ellipse extents, far above their rounding error.
_EXTENT_MARGIN = 1e-9
# Fixed chunk counts make the order of floating-point sums independent of the thread count.
GAUSSIAN_CHUNKS = 256
_KEY_INDEX_MASK = 0xFFFFFFFF
_EXP_MINUS_HALF = math.exp(-0.5)
# A tile row's live pixels are the bits of one int64.
MAX_TILE_SIZE = 64
# Tile-local pixel index p = row << _ROW_SHIFT | column, so that no kernel divides by the tile size.
_ROW_SHIFT = 6

# Columns of a slot's float record: mean2d, conic, opacity, and the sigma up to which it lists pixels.
SF_MX, SF_MY, SF_A, SF_B, SF_C, SF_OPACITY, SF_LIMIT = range(7)
SF_COLUMNS = 7
# Columns of a slot's int record: its splat's pixel rect clipped to the slot's tile (inclusive).
SI_U_LO, SI_U_HI, SI_V_LO, SI_V_HI = range(4)
SI_COLUMNS = 4
# Per-slot gradient columns before the colour channels: mean2d x, y, conic a, b, c, opacity.
N_GRAD_GEOMETRY = 6

# nogil: the kernels run on plain threads (see `reconstruction.parallel`); error_model numpy: no ZeroDivision checks.
_OPTS = {"cache": True, "error_model": "numpy", "nogil": True}
# Projection and compositing let multiply-adds fuse (one rounding instead of two): faster
# (benchmarks/results/rasterizer.md), and results move by ~1e-15 relative.
_FUSED = {"contract"}


# Gathers by splat index (per-tile records, per-pair sums) read rows scattered over a few ten MB: hinting the row
# this many items ahead lets its cache miss overlap the work on the current one.
_PREFETCH_AHEAD = 16


@intrinsic
def _prefetch(typingctx, array, index):
    """Hints the CPU to bring array[index] (a 1-D array) into cache, for reading; no effect on results."""
    if not (isinstance(array, types.Array) and array.ndim == 1 and isinstance(index, types.Integer)):
        return None

    def codegen(context, builder, signature, args):
        array_type = signature.args[0]
        data = context.make_array(array_type)(context, builder, args[0])
        at = context.cast(builder, args[1], signature.args[1], types.intp)
        ptr = builder.bitcast(cgutils.get_item_pointer(context, builder, array_type, data, [at]), ir.IntType(8).as_pointer())
        i32 = ir.IntType(32)
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.VoidType(), [ptr.type, i32, i32, i32]), "llvm.prefetch.p0i8")
        # read, high temporal locality, data cache
        builder.call(fn, [ptr, ir.Constant(i32, 0), ir.Constant(i32, 3), ir.Constant(i32, 1)])
        return context.get_dummy_value()

    return types.void(array, index), codegen


def _packs_by_table(features: str) -> bool:
    """Whether the listing packs kept lanes by AVX2 permutes, for a target with these LLVM features
    ("+avx2,-avx512f,..."): with AVX2 and no AVX-512, where LLVM lowers the vector compress to scalar moves
    (measured: benchmarks/results/rasterizer.md)."""
    flags = set(features.split(","))
    return "+avx2" in flags and "+avx512f" not in flags


def _pack4_indices(mask: int) -> list[int]:
    """The permute's 32-bit source indices that move the 64-bit lanes set in `mask` (of four) to the front, in order."""
    lanes = [j for j in range(4) if mask >> j & 1]
    return [i for j in lanes for i in (2 * j, 2 * j + 1)] + [0] * (8 - 2 * len(lanes))


def _ctpop(builder, bits: int):
    return cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.IntType(bits), [ir.IntType(bits)]), f"llvm.ctpop.i{bits}")


def _store_packed_by_table(builder, value, keep_bits, data, array_type, context, m) -> None:
    """Stores the lanes of value <8 x 64-bit> whose bit is set in keep_bits (i8) packed at array[m:]: each half of four
    lanes is moved to the front by one 32-bit permute (vpermd, which LLVM may emit as vpermps) through a 16-entry table
    (a 64-bit lane is two 32-bit ones) and stored whole, the second half right after the first half's kept lanes."""
    i8, i32, i64 = ir.IntType(8), ir.IntType(32), ir.IntType(64)
    v8i32 = ir.VectorType(i32, 8)
    table_type = ir.ArrayType(v8i32, 16)
    table = builder.module.globals.get("cadsplat_pack4_indices")
    if table is None:
        table = ir.GlobalVariable(builder.module, table_type, "cadsplat_pack4_indices")
        table.linkage = "internal"
        table.global_constant = True
        table.initializer = ir.Constant(table_type, [ir.Constant(v8i32, _pack4_indices(mask)) for mask in range(16)])
    permd = cgutils.get_or_insert_function(builder.module, ir.FunctionType(v8i32, [v8i32, v8i32]), "llvm.x86.avx2.permd")
    low = builder.and_(keep_bits, ir.Constant(i8, 15))
    halves = (
        (0, low, m),
        (1, builder.lshr(keep_bits, ir.Constant(i8, 4)), builder.add(m, builder.zext(builder.call(_ctpop(builder, 8), [low]), i64))),
    )
    for half, nibble, at_m in halves:
        quad = builder.shuffle_vector(
            value, ir.Constant(value.type, ir.Undefined), ir.Constant(ir.VectorType(i32, 4), [4 * half + j for j in range(4)])
        )
        indices = builder.load(builder.gep(table, [ir.Constant(i32, 0), builder.zext(nibble, i32)]), align=32)
        packed = builder.call(permd, [builder.bitcast(quad, v8i32), indices])
        at = cgutils.get_item_pointer(context, builder, array_type, data, [at_m])
        builder.store(builder.bitcast(packed, quad.type), builder.bitcast(at, quad.type.as_pointer()), align=8)


# The listing evaluates this many pixels of a row at once (one AVX-512 register of float64).
LIST_LANES = 8


@intrinsic
def _list_lanes(typingctx, buf_p, buf_sigma, m, px0, p0, row_bits, first_bit, mx, dy, a, b, half_c_dy2, limit):
    """Lists pixels px0 + l of one row, l < LIST_LANES: sigma = 0.5 a dx^2 + half_c_dy2 + b dx dy with dx = px0 + l + 0.5
    - mx, kept where bit first_bit + l of row_bits is set and sigma <= limit. The shift is logical, so lanes past bit 63
    (past a 64-px tile's last column) are never kept. The kept sigmas and tile-local indices p0 + l are packed to the
    front of one register each and stored whole at buf_sigma[m:] and buf_p[m:] (both need LIST_LANES - 1 items of room
    past the last kept one); returns m plus the number kept.

    A scalar listing advances its cursor pixel by pixel, a chain the compiler cannot vectorise. LLVM's vector compress
    is one instruction with AVX-512 (vcompresspd) and a sequence of scalar moves elsewhere; with AVX2 and no AVX-512
    each half of four lanes is packed by one permute instead (`_packs_by_table`). Packing only moves values, so the
    lists are the same on any CPU; the arithmetic is the scalar listing's, operation for operation, so are the sigmas.
    """
    if not (
        isinstance(buf_p, types.Array)
        and buf_p.ndim == 1
        and buf_p.dtype == types.int64
        and isinstance(buf_sigma, types.Array)
        and buf_sigma.ndim == 1
        and buf_sigma.dtype == types.float64
    ):
        return None

    def codegen(context, builder, signature, args):
        (p_array, sigma_array, m_, px0_, p0_, bits_, first_bit_, mx_, dy_, a_, b_, half_c_dy2_, limit_) = args
        f64, i64 = ir.DoubleType(), ir.IntType(64)
        vf, vi, vb = ir.VectorType(f64, LIST_LANES), ir.VectorType(i64, LIST_LANES), ir.VectorType(ir.IntType(1), LIST_LANES)
        zeros = ir.Constant(ir.VectorType(ir.IntType(32), LIST_LANES), [0] * LIST_LANES)

        def splat(value, vector_type):
            undef = ir.Constant(vector_type, ir.Undefined)
            return builder.shuffle_vector(builder.insert_element(undef, value, ir.Constant(ir.IntType(32), 0)), undef, zeros)

        lanes = ir.Constant(vi, list(range(LIST_LANES)))
        # px0 + l + 0.5 as float(px0) + (l + 0.5): exact either way (small integers and halves), but without AVX-512 an
        # int64 vector converts lane by lane (8 scalar conversions and as many moves a call).
        centres = builder.fadd(splat(builder.sitofp(px0_, f64), vf), ir.Constant(vf, [l + 0.5 for l in range(LIST_LANES)]))
        dx = builder.fsub(centres, splat(mx_, vf))
        sigma = builder.fmul(builder.fmul(splat(builder.fmul(ir.Constant(f64, 0.5), a_), vf), dx), dx)
        sigma = builder.fadd(sigma, splat(half_c_dy2_, vf))
        sigma = builder.fadd(sigma, builder.fmul(builder.fmul(splat(b_, vf), dx), splat(dy_, vf)))
        within = builder.fcmp_ordered("<=", sigma, splat(limit_, vf))
        row_bits = builder.trunc(builder.lshr(bits_, first_bit_), ir.IntType(LIST_LANES))
        by_table = _packs_by_table(context.codegen().magic_tuple()[2])
        if by_table:
            # The comparison's lanes become an integer mask and meet the row's bits there, instead of the bits being
            # spread into a vector mask and gathered back (benchmarks/results/rasterizer.md).
            keep_bits = builder.and_(builder.bitcast(within, ir.IntType(LIST_LANES)), row_bits)
        else:
            keep = builder.and_(within, builder.bitcast(row_bits, vb))
            keep_bits = builder.bitcast(keep, ir.IntType(LIST_LANES))
        values = ((sigma, sigma_array, signature.args[1]), (builder.add(splat(p0_, vi), lanes), p_array, signature.args[0]))
        for value, array, array_type in values:
            data = context.make_array(array_type)(context, builder, array)
            if by_table:
                _store_packed_by_table(builder, value, keep_bits, data, array_type, context, m_)
                continue
            vt = value.type
            compress = cgutils.get_or_insert_function(
                builder.module,
                ir.FunctionType(vt, [vt, vb, vt]),
                f"llvm.experimental.vector.compress.v{LIST_LANES}{'f64' if vt == vf else 'i64'}",
            )
            packed = builder.call(compress, [value, keep, ir.Constant(vt, ir.Undefined)])
            at = cgutils.get_item_pointer(context, builder, array_type, data, [m_])
            builder.store(packed, builder.bitcast(at, vt.as_pointer()), align=8)
        return builder.add(m_, builder.zext(builder.call(_ctpop(builder, LIST_LANES), [keep_bits]), i64))

    return types.int64(buf_p, buf_sigma, *([types.int64] * 5), *([types.float64] * 6)), codegen


@njit(inline="always", **_OPTS)
def _chunk_bounds(chunk: int, n_chunks: int, n: int) -> tuple[int, int]:
    return chunk * n // n_chunks, (chunk + 1) * n // n_chunks


@njit(inline="always", **_OPTS)
def _unit_quaternion_of(qw, qx, qy, qz):
    """(1 / |q|, w, x, y, z) of q / |q| for a wxyz quaternion q."""
    inv_norm = 1.0 / math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    return inv_norm, qw * inv_norm, qx * inv_norm, qy * inv_norm, qz * inv_norm


@njit(inline="always", **_OPTS)
def _unit_quaternion(quat):
    """`_unit_quaternion_of` a quaternion row quat [4]."""
    return _unit_quaternion_of(quat[0], quat[1], quat[2], quat[3])


@njit(inline="always", **_OPTS)
def _rotation_matrix(w, x, y, z):
    """Row-major entries of R(q) for a unit wxyz quaternion."""
    return (
        1.0 - 2.0 * (y * y + z * z),
        2.0 * (x * y - w * z),
        2.0 * (x * z + w * y),
        2.0 * (x * y + w * z),
        1.0 - 2.0 * (x * x + z * z),
        2.0 * (y * z - w * x),
        2.0 * (x * z - w * y),
        2.0 * (y * z + w * x),
        1.0 - 2.0 * (x * x + y * y),
    )


@njit(inline="always", **_OPTS)
def _factor_product(m00, m01, m02, m10, m11, m12, m20, m21, m22):
    """Upper triangle (c00, c01, c02, c11, c12, c22) of M M^T."""
    return (
        m00 * m00 + m01 * m01 + m02 * m02,
        m00 * m10 + m01 * m11 + m02 * m12,
        m00 * m20 + m01 * m21 + m02 * m22,
        m10 * m10 + m11 * m11 + m12 * m12,
        m10 * m20 + m11 * m21 + m12 * m22,
        m20 * m20 + m21 * m21 + m22 * m22,
    )


@njit(inline="always", **_OPTS)
def _camera_covariance(r00, r01, r02, r10, r11, r12, r20, r21, r22, c00, c01, c02, c11, c12, c22):
    """Upper triangle (w00, w01, w02, w11, w12, w22) of W = R cov R^T, R given row-major, cov by its upper triangle."""
    t00 = r00 * c00 + r01 * c01 + r02 * c02
    t01 = r00 * c01 + r01 * c11 + r02 * c12
    t02 = r00 * c02 + r01 * c12 + r02 * c22
    t10 = r10 * c00 + r11 * c01 + r12 * c02
    t11 = r10 * c01 + r11 * c11 + r12 * c12
    t12 = r10 * c02 + r11 * c12 + r12 * c22
    t20 = r20 * c00 + r21 * c01 + r22 * c02
    t21 = r20 * c01 + r21 * c11 + r22 * c12
    t22 = r20 * c02 + r21 * c12 + r22 * c22
    return (
        t00 * r00 + t01 * r01 + t02 * r02,
        t00 * r10 + t01 * r11 + t02 * r12,
        t00 * r20 + t01 * r21 + t02 * r22,
        t10 * r10 + t11 * r11 + t12 * r12,
        t10 * r20 + t11 * r21 + t12 * r22,
        t20 * r20 + t21 * r21 + t22 * r22,
    )


@njit(inline="always", **_OPTS)
def _clamp_limits(Ks, width: int, height: int) -> np.ndarray:
    """gsplat's limits on x/z and y/z per camera [C, 4] (x_lo, x_hi, y_lo, y_hi): the image plus 30% of the
    half field of view on each side. Computed once per call, not per Gaussian (six divisions each)."""
    limits = np.empty((Ks.shape[0], 4))
    for c in range(Ks.shape[0]):
        fx, fy, cx, cy = Ks[c, 0, 0], Ks[c, 1, 1], Ks[c, 0, 2], Ks[c, 1, 2]
        tan_fovx = 0.5 * width / fx
        tan_fovy = 0.5 * height / fy
        limits[c, 0] = -(cx / fx + 0.3 * tan_fovx)
        limits[c, 1] = (width - cx) / fx + 0.3 * tan_fovx
        limits[c, 2] = -(cy / fy + 0.3 * tan_fovy)
        limits[c, 3] = (height - cy) / fy + 0.3 * tan_fovy
    return limits


@njit(inline="always", **_OPTS)
def _jacobian(mx, my, mz, rz, fx, fy, x_lo, x_hi, y_lo, y_hi):
    """Non-zero entries (j00, j02, j11, j12) of the perspective Jacobian, with x/z and y/z clamped (rz = 1 / mz).

    The clamp keeps Gaussians far outside the view (and those straddling the near plane) from getting
    unbounded screen-space covariances; the clamped coordinate then follows z, not x or y.
    """
    tx = mz * min(x_hi, max(x_lo, mx * rz))
    ty = mz * min(y_hi, max(y_lo, my * rz))
    return fx * rz, -fx * tx * rz * rz, fy * rz, -fy * ty * rz * rz


@njit(inline="always", **_OPTS)
def _covariance2d(w00, w01, w02, w11, w12, w22, j00, j02, j11, j12, eps2d):
    """J W J^T + eps2d I as (s00, s01, s11), W given by its upper triangle."""
    s00 = j00 * j00 * w00 + 2.0 * j00 * j02 * w02 + j02 * j02 * w22 + eps2d
    s01 = j00 * j11 * w01 + j00 * j12 * w02 + j02 * j11 * w12 + j02 * j12 * w22
    s11 = j11 * j11 * w11 + 2.0 * j11 * j12 * w12 + j12 * j12 * w22 + eps2d
    return s00, s01, s11


@njit(inline="always", **_OPTS)
def _tile_shift(tile_size: int) -> int:
    """log2(tile_size) for a power of two, else -1: pixel // tile_size as a shift, not a 40-cycle integer division."""
    return int(math.log2(tile_size)) if tile_size > 0 and tile_size & (tile_size - 1) == 0 else -1


@njit(inline="always", **_OPTS)
def _tile_of(px: int, tile_size: int, shift: int) -> int:
    """Tile index of pixel px >= 0 (shift from `_tile_shift`)."""
    return px >> shift if shift >= 0 else px // tile_size


@njit(inline="always", **_OPTS)
def _pixel_rect(u, v, half_x, half_y, width, height):
    """Inclusive pixel range (u_lo, u_hi, v_lo, v_hi) of the centres inside the bounding box of the alpha >= 1/255
    ellipse sigma <= ln(255 opacity) of a splat at (u, v), clipped to the image. Empty when u_lo > u_hi or v_lo > v_hi.

    The ellipse spans |dx| <= half_x = sqrt(2 ln(255 opacity) cov2d_xx) (likewise y): the extent gsplat's radius rounds
    up, so the rect holds every pixel the radius box holds that could be shaded, and for small splats about half of
    them. A pixel u belongs when its centre u + 0.5 is inside.
    """
    ext_x = half_x * (1.0 + _EXTENT_MARGIN) + _EXTENT_MARGIN
    ext_y = half_y * (1.0 + _EXTENT_MARGIN) + _EXTENT_MARGIN
    # Clip in float first so that huge extents cannot overflow the integer conversion.
    u_lo = math.ceil(max(u - ext_x - 0.5, -1.0))
    u_hi = math.floor(min(u + ext_x - 0.5, 1.0 * width))
    v_lo = math.ceil(max(v - ext_y - 0.5, -1.0))
    v_hi = math.floor(min(v + ext_y - 0.5, 1.0 * height))
    return max(0, u_lo), min(width - 1, u_hi), max(0, v_lo), min(height - 1, v_hi)


@njit(inline="always", **_OPTS)
def _chunk_covariances(lo, hi, means, quats, scales, opacities, active, cols, cov, two_log) -> None:
    """The per-Gaussian part of the projection for Gaussians lo..hi-1, as columns (structure of arrays) that the camera
    pass reads with vector loads: cols [11, >= hi - lo] (the world mean, the quaternion and the scales, copied so that
    the covariances below run on contiguous columns, then sqrt(two_log), the box's extent in standard deviations), the
    covariance's upper triangle cov [6, >= hi - lo], and two_log [>= hi - lo] = 2 ln(255 opacity), 0 for a Gaussian that
    is not drawn (gsplat 1.5.3's opacity-aware box: alpha >= 1/255 needs sigma <= ln(255 opacity))."""
    for i in range(hi - lo):
        g = lo + i
        for k in range(3):
            cols[k, i] = means[g, k]
        for k in range(4):
            cols[3 + k, i] = quats[g, k]
        for k in range(3):
            cols[7 + k, i] = scales[g, k]
        opacity = opacities[g]
        # `not >=` also culls NaN opacities.
        two_log[i] = 2.0 * math.log(opacity * 255.0) if active[g] and opacity >= ALPHA_THRESHOLD else 0.0
    # Branch-free over whole columns: 8 Gaussians a vector.
    for i in range(hi - lo):
        _, w, x, y, z = _unit_quaternion_of(cols[3, i], cols[4, i], cols[5, i], cols[6, i])
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = _rotation_matrix(w, x, y, z)
        s0, s1, s2 = cols[7, i], cols[8, i], cols[9, i]
        cols[10, i] = math.sqrt(two_log[i])
        c00, c01, c02, c11, c12, c22 = _factor_product(
            r00 * s0, r01 * s1, r02 * s2, r10 * s0, r11 * s1, r12 * s2, r20 * s0, r21 * s1, r22 * s2
        )
        cov[0, i] = c00
        cov[1, i] = c01
        cov[2, i] = c02
        cov[3, i] = c11
        cov[4, i] = c12
        cov[5, i] = c22


@njit(fastmath=_FUSED, **_OPTS)
def project_forward(
    chunk_lo,
    chunk_hi,
    n_chunks,
    means,
    quats,
    scales,
    opacities,
    active,
    viewmats,
    Ks,
    width,
    height,
    near,
    far,
    eps2d,
    tile_size,
    means2d,
    conics,
    depths,
    radii,
    two_logs,
    rects,
    tile_counts,
    hist,
) -> None:
    """Projects N Gaussians into C cameras; culled entries keep the zeros they were allocated with.

    Inputs: means [N, 3], quats [N, 4] (wxyz, any norm), scales [N, 3], opacities [N], active [N] bool,
    viewmats [C, 4, 4], Ks [C, 3, 3]. Outputs: means2d [C, N, 2] f64, conics [C, N, 3] f64,
    depths [C, N] f64, radii [C, N, 2] int32.

    With tile_size > 0 it also lays out the binning's first pass while each splat is in registers:
    two_logs [N] = 2 ln(255 opacity) of the drawn Gaussians, each visible pair's pixel rect rects [C * N, 4] and
    tile count tile_counts [C * N] (zero-initialised; zero for culled pairs and rects without a pixel centre), and
    hist [n_chunks, C * tiles_per_cam] (zero-initialised), the slots of chunk's pairs per tile: a counting
    sort's histogram. Chunks are fixed ranges of Gaussians, all cameras each.

    Each chunk runs in passes: the per-Gaussian covariances, then per camera one branch-free pass over all of the
    chunk's Gaussians (the arithmetic, 8 Gaussians a vector) and one that culls and writes (the branches).
    """
    n = means.shape[0]
    n_cams = viewmats.shape[0]
    tiles_x = -(-width // tile_size) if tile_size > 0 else 0
    tiles_per_cam = tiles_x * (-(-height // tile_size)) if tile_size > 0 else 0
    shift = _tile_shift(tile_size)
    limits = _clamp_limits(Ks, width, height)
    longest = 0
    for chunk in range(chunk_lo, chunk_hi):
        lo, hi = _chunk_bounds(chunk, n_chunks, n)
        longest = max(longest, hi - lo)
    cols = np.empty((11, longest))
    cov = np.empty((6, longest))
    two_log = np.empty(longest)
    # Per camera: depth, pixel position, the half extents of the alpha >= 1/255 box, the conic and the 2D determinant.
    screen = np.empty((9, longest))
    for chunk in range(chunk_lo, chunk_hi):
        lo, hi = _chunk_bounds(chunk, n_chunks, n)
        chunk_hist = hist[chunk]
        _chunk_covariances(lo, hi, means, quats, scales, opacities, active, cols, cov, two_log)
        if tile_size > 0:
            for i in range(hi - lo):
                if two_log[i] != 0.0:
                    two_logs[lo + i] = two_log[i]
        for c in range(n_cams):
            # The camera as scalars: loop-invariant values the compiler need not reload after each store.
            r00, r01, r02, t0 = viewmats[c, 0, 0], viewmats[c, 0, 1], viewmats[c, 0, 2], viewmats[c, 0, 3]
            r10, r11, r12, t1 = viewmats[c, 1, 0], viewmats[c, 1, 1], viewmats[c, 1, 2], viewmats[c, 1, 3]
            r20, r21, r22, t2 = viewmats[c, 2, 0], viewmats[c, 2, 1], viewmats[c, 2, 2], viewmats[c, 2, 3]
            fx, fy = Ks[c, 0, 0], Ks[c, 1, 1]
            cx, cy = Ks[c, 0, 2], Ks[c, 1, 2]
            x_lo, x_hi, y_lo, y_hi = limits[c, 0], limits[c, 1], limits[c, 2], limits[c, 3]
            for i in range(hi - lo):
                p0, p1, p2 = cols[0, i], cols[1, i], cols[2, i]
                mx = r00 * p0 + r01 * p1 + r02 * p2 + t0
                my = r10 * p0 + r11 * p1 + r12 * p2 + t1
                mz = r20 * p0 + r21 * p1 + r22 * p2 + t2
                w00, w01, w02, w11, w12, w22 = _camera_covariance(
                    r00,
                    r01,
                    r02,
                    r10,
                    r11,
                    r12,
                    r20,
                    r21,
                    r22,
                    cov[0, i],
                    cov[1, i],
                    cov[2, i],
                    cov[3, i],
                    cov[4, i],
                    cov[5, i],
                )
                # One division per divisor and multiplications after: the projection's divisions and square roots
                # were most of its time. Values move by an ulp.
                rz = 1.0 / mz
                j00, j02, j11, j12 = _jacobian(mx, my, mz, rz, fx, fy, x_lo, x_hi, y_lo, y_hi)
                s00, s01, s11 = _covariance2d(w00, w01, w02, w11, w12, w22, j00, j02, j11, j12, eps2d)
                det = s00 * s11 - s01 * s01
                inv_det = 1.0 / det
                # Square roots of negative variances are NaN here; the culling pass drops those splats (det <= 0).
                screen[0, i] = mz
                screen[1, i] = fx * mx * rz + cx
                screen[2, i] = fy * my * rz + cy
                screen[3, i] = cols[10, i] * math.sqrt(s00)
                screen[4, i] = cols[10, i] * math.sqrt(s11)
                screen[5, i] = s11 * inv_det
                screen[6, i] = -s01 * inv_det
                screen[7, i] = s00 * inv_det
                screen[8, i] = det
            for i in range(hi - lo):
                if two_log[i] == 0.0:
                    continue
                mz = screen[0, i]
                if not (mz > near and mz < far):
                    continue
                if not screen[8, i] > 0.0:
                    continue
                half_x, half_y = screen[3, i], screen[4, i]
                # Capped so that absurd covariances cannot overflow the integer conversion.
                rx = math.ceil(min(half_x, 1e9))
                ry = math.ceil(min(half_y, 1e9))
                if rx <= 0 or ry <= 0:
                    continue
                u, v = screen[1, i], screen[2, i]
                if u + rx <= 0.0 or u - rx >= width or v + ry <= 0.0 or v - ry >= height:
                    continue
                g = lo + i
                means2d[c, g, 0] = u
                means2d[c, g, 1] = v
                conics[c, g, 0] = screen[5, i]
                conics[c, g, 1] = screen[6, i]
                conics[c, g, 2] = screen[7, i]
                depths[c, g] = mz
                radii[c, g, 0] = rx
                radii[c, g, 1] = ry
                if tile_size <= 0:
                    continue
                u_lo, u_hi, v_lo, v_hi = _pixel_rect(u, v, half_x, half_y, width, height)
                if u_lo > u_hi or v_lo > v_hi:
                    continue
                cg = c * n + g
                rects[cg, 0] = u_lo
                rects[cg, 1] = u_hi
                rects[cg, 2] = v_lo
                rects[cg, 3] = v_hi
                tx0, tx1 = _tile_of(u_lo, tile_size, shift), _tile_of(u_hi, tile_size, shift)
                ty0, ty1 = _tile_of(v_lo, tile_size, shift), _tile_of(v_hi, tile_size, shift)
                tile_counts[cg] = (tx1 - tx0 + 1) * (ty1 - ty0 + 1)
                base = c * tiles_per_cam
                # Most splats touch one tile, so that case skips the loops' unpredictable trip counts (benchmarks/results/rasterizer.md).
                if tx0 == tx1 and ty0 == ty1:
                    chunk_hist[base + ty0 * tiles_x + tx0] += 1
                    continue
                for ty in range(ty0, ty1 + 1):
                    for tx in range(tx0, tx1 + 1):
                        chunk_hist[base + ty * tiles_x + tx] += 1


@njit(fastmath=_FUSED, **_OPTS)
def project_backward(
    chunk_lo,
    chunk_hi,
    means,
    quats,
    scales,
    viewmats,
    Ks,
    width,
    height,
    radii,
    conics,
    v_means2d,
    v_conics,
    want_cov,
    want_viewmats,
    v_means,
    v_quats,
    v_scales,
    v_viewmats_chunks,
) -> None:
    """VJP of `project_forward` for the visible entries.

    v_means2d [C, N, 2] and v_conics [C, N, 3] (gradients w.r.t. (a, b, c)) come in; v_means [N, 3] is written and,
    if want_cov, v_quats [N, 4] and v_scales [N, 3] (all zero-initialised by the caller); if want_viewmats,
    per-chunk viewmat gradients are accumulated into v_viewmats_chunks [n_chunks, C, 3, 4] (the caller
    sums the chunks). Symmetric matrices (cov, W, their gradients) are carried as upper-triangle scalars.
    """
    n = means.shape[0]
    n_cams = viewmats.shape[0]
    n_chunks = v_viewmats_chunks.shape[0]
    limits = _clamp_limits(Ks, width, height)
    for chunk in range(chunk_lo, chunk_hi):
        lo, hi = _chunk_bounds(chunk, n_chunks, n)
        for g in range(lo, hi):
            seen = False
            for c in range(n_cams):
                seen = seen or radii[c, g, 0] > 0
            if not seen:
                continue
            inv_qnorm, w, x, y, z = _unit_quaternion(quats[g])
            r00, r01, r02, r10, r11, r12, r20, r21, r22 = _rotation_matrix(w, x, y, z)
            s0, s1, s2 = scales[g, 0], scales[g, 1], scales[g, 2]
            m00, m01, m02 = r00 * s0, r01 * s1, r02 * s2
            m10, m11, m12 = r10 * s0, r11 * s1, r12 * s2
            m20, m21, m22 = r20 * s0, r21 * s1, r22 * s2
            c00, c01, c02, c11, c12, c22 = _factor_product(m00, m01, m02, m10, m11, m12, m20, m21, m22)
            # dL/dcov, symmetric.
            vc00 = vc01 = vc02 = vc11 = vc12 = vc22 = 0.0
            vmx_w = 0.0
            vmy_w = 0.0
            vmz_w = 0.0
            for c in range(n_cams):
                if radii[c, g, 0] <= 0:
                    continue
                vm = viewmats[c]
                mx = vm[0, 0] * means[g, 0] + vm[0, 1] * means[g, 1] + vm[0, 2] * means[g, 2] + vm[0, 3]
                my = vm[1, 0] * means[g, 0] + vm[1, 1] * means[g, 1] + vm[1, 2] * means[g, 2] + vm[1, 3]
                mz = vm[2, 0] * means[g, 0] + vm[2, 1] * means[g, 1] + vm[2, 2] * means[g, 2] + vm[2, 3]
                w00, w01, w02, w11, w12, w22 = _camera_covariance(
                    vm[0, 0],
                    vm[0, 1],
                    vm[0, 2],
                    vm[1, 0],
                    vm[1, 1],
                    vm[1, 2],
                    vm[2, 0],
                    vm[2, 1],
                    vm[2, 2],
                    c00,
                    c01,
                    c02,
                    c11,
                    c12,
                    c22,
                )
                fx, fy = Ks[c, 0, 0], Ks[c, 1, 1]
                x_lo, x_hi, y_lo, y_hi = limits[c, 0], limits[c, 1], limits[c, 2], limits[c, 3]
                rz = 1.0 / mz
                j00, j02, j11, j12 = _jacobian(mx, my, mz, rz, fx, fy, x_lo, x_hi, y_lo, y_hi)
                a, b, cc = conics[c, g, 0], conics[c, g, 1], conics[c, g, 2]
                # dL/dQ as a symmetric matrix V (b appears twice in Q); dSigma = -Q V Q.
                v00, v01, v11 = v_conics[c, g, 0], 0.5 * v_conics[c, g, 1], v_conics[c, g, 2]
                p00 = a * v00 + b * v01
                p01 = a * v01 + b * v11
                p10 = b * v00 + cc * v01
                p11 = b * v01 + cc * v11
                g00 = -(p00 * a + p01 * b)
                g01 = -(p00 * b + p01 * cc)
                g11 = -(p10 * b + p11 * cc)
                # G J, with J = [[j00, 0, j02], [0, j11, j12]].
                gj00 = g00 * j00
                gj01 = g01 * j11
                gj02 = g00 * j02 + g01 * j12
                gj10 = g01 * j00
                gj11 = g11 * j11
                gj12 = g01 * j02 + g11 * j12
                # dL/dJ = 2 G J W (only the structurally non-zero entries matter).
                vj00 = 2.0 * (gj00 * w00 + gj01 * w01 + gj02 * w02)
                vj02 = 2.0 * (gj00 * w02 + gj01 * w12 + gj02 * w22)
                vj11 = 2.0 * (gj10 * w01 + gj11 * w11 + gj12 * w12)
                vj12 = 2.0 * (gj10 * w02 + gj11 * w12 + gj12 * w22)
                # dL/dW = J^T G J, symmetric.
                a00 = j00 * gj00
                a01 = j00 * gj01
                a02 = j00 * gj02
                a11 = j11 * gj11
                a12 = j11 * gj12
                a22 = j02 * gj02 + j12 * gj12
                # Camera-frame mean: through mean2d and through J.
                rz2 = rz * rz
                rz3 = rz2 * rz
                vu, vv = v_means2d[c, g, 0], v_means2d[c, g, 1]
                vmx = fx * rz * vu
                vmy = fy * rz * vv
                vmz = -(fx * mx * vu + fy * my * vv) * rz2 - fx * rz2 * vj00 - fy * rz2 * vj11
                if x_lo <= mx * rz <= x_hi:
                    vmx += -fx * rz2 * vj02
                    vmz += 2.0 * fx * mx * rz3 * vj02
                else:
                    vmz += fx * (mz * min(x_hi, max(x_lo, mx * rz))) * rz3 * vj02
                if y_lo <= my * rz <= y_hi:
                    vmy += -fy * rz2 * vj12
                    vmz += 2.0 * fy * my * rz3 * vj12
                else:
                    vmz += fy * (mz * min(y_hi, max(y_lo, my * rz))) * rz3 * vj12
                if want_cov:
                    # W = V cov V^T (V = vm[:3, :3]): dL/dcov += V^T A V, with B = V^T A first.
                    b00 = vm[0, 0] * a00 + vm[1, 0] * a01 + vm[2, 0] * a02
                    b01 = vm[0, 0] * a01 + vm[1, 0] * a11 + vm[2, 0] * a12
                    b02 = vm[0, 0] * a02 + vm[1, 0] * a12 + vm[2, 0] * a22
                    b10 = vm[0, 1] * a00 + vm[1, 1] * a01 + vm[2, 1] * a02
                    b11 = vm[0, 1] * a01 + vm[1, 1] * a11 + vm[2, 1] * a12
                    b12 = vm[0, 1] * a02 + vm[1, 1] * a12 + vm[2, 1] * a22
                    b20 = vm[0, 2] * a00 + vm[1, 2] * a01 + vm[2, 2] * a02
                    b21 = vm[0, 2] * a01 + vm[1, 2] * a11 + vm[2, 2] * a12
                    b22 = vm[0, 2] * a02 + vm[1, 2] * a12 + vm[2, 2] * a22
                    vc00 += b00 * vm[0, 0] + b01 * vm[1, 0] + b02 * vm[2, 0]
                    vc01 += b00 * vm[0, 1] + b01 * vm[1, 1] + b02 * vm[2, 1]
                    vc02 += b00 * vm[0, 2] + b01 * vm[1, 2] + b02 * vm[2, 2]
                    vc11 += b10 * vm[0, 1] + b11 * vm[1, 1] + b12 * vm[2, 1]
                    vc12 += b10 * vm[0, 2] + b11 * vm[1, 2] + b12 * vm[2, 2]
                    vc22 += b20 * vm[0, 2] + b21 * vm[1, 2] + b22 * vm[2, 2]
                if want_viewmats:
                    # dL/dV = 2 A V cov + (dL/dm_cam) m^T, and dL/dt = dL/dm_cam.
                    v_view = v_viewmats_chunks[chunk, c]
                    vmc = (vmx, vmy, vmz)
                    for i in range(3):
                        ai0 = a00 if i == 0 else (a01 if i == 1 else a02)
                        ai1 = a01 if i == 0 else (a11 if i == 1 else a12)
                        ai2 = a02 if i == 0 else (a12 if i == 1 else a22)
                        # Row i of A V.
                        av0 = ai0 * vm[0, 0] + ai1 * vm[1, 0] + ai2 * vm[2, 0]
                        av1 = ai0 * vm[0, 1] + ai1 * vm[1, 1] + ai2 * vm[2, 1]
                        av2 = ai0 * vm[0, 2] + ai1 * vm[1, 2] + ai2 * vm[2, 2]
                        v_view[i, 0] += 2.0 * (av0 * c00 + av1 * c01 + av2 * c02) + vmc[i] * means[g, 0]
                        v_view[i, 1] += 2.0 * (av0 * c01 + av1 * c11 + av2 * c12) + vmc[i] * means[g, 1]
                        v_view[i, 2] += 2.0 * (av0 * c02 + av1 * c12 + av2 * c22) + vmc[i] * means[g, 2]
                        v_view[i, 3] += vmc[i]
                vmx_w += vm[0, 0] * vmx + vm[1, 0] * vmy + vm[2, 0] * vmz
                vmy_w += vm[0, 1] * vmx + vm[1, 1] * vmy + vm[2, 1] * vmz
                vmz_w += vm[0, 2] * vmx + vm[1, 2] * vmy + vm[2, 2] * vmz
            v_means[g, 0] = vmx_w
            v_means[g, 1] = vmy_w
            v_means[g, 2] = vmz_w
            if not want_cov:
                continue
            # cov = M M^T with M = R diag(s): dL/dM = 2 dL/dcov M.
            f00 = 2.0 * (vc00 * m00 + vc01 * m10 + vc02 * m20)
            f01 = 2.0 * (vc00 * m01 + vc01 * m11 + vc02 * m21)
            f02 = 2.0 * (vc00 * m02 + vc01 * m12 + vc02 * m22)
            f10 = 2.0 * (vc01 * m00 + vc11 * m10 + vc12 * m20)
            f11 = 2.0 * (vc01 * m01 + vc11 * m11 + vc12 * m21)
            f12 = 2.0 * (vc01 * m02 + vc11 * m12 + vc12 * m22)
            f20 = 2.0 * (vc02 * m00 + vc12 * m10 + vc22 * m20)
            f21 = 2.0 * (vc02 * m01 + vc12 * m11 + vc22 * m21)
            f22 = 2.0 * (vc02 * m02 + vc12 * m12 + vc22 * m22)
            v_scales[g, 0] = f00 * r00 + f10 * r10 + f20 * r20
            v_scales[g, 1] = f01 * r01 + f11 * r11 + f21 * r21
            v_scales[g, 2] = f02 * r02 + f12 * r12 + f22 * r22
            # dL/dR = dL/dM diag(s), then through R(q) of the unit quaternion, then through the normalisation.
            q00, q01, q02 = f00 * s0, f01 * s1, f02 * s2
            q10, q11, q12 = f10 * s0, f11 * s1, f12 * s2
            q20, q21, q22 = f20 * s0, f21 * s1, f22 * s2
            vw = 2.0 * (-z * q01 + y * q02 + z * q10 - x * q12 - y * q20 + x * q21)
            vx = 2.0 * (y * q01 + z * q02 + y * q10 - 2.0 * x * q11 - w * q12 + z * q20 + w * q21 - 2.0 * x * q22)
            vy = 2.0 * (-2.0 * y * q00 + x * q01 + w * q02 + x * q10 + z * q12 - w * q20 + z * q21 - 2.0 * y * q22)
            vz = 2.0 * (-2.0 * z * q00 - w * q01 + x * q02 + w * q10 - 2.0 * z * q11 + y * q12 + x * q20 + y * q21)
            dot = w * vw + x * vx + y * vy + z * vz
            v_quats[g, 0] = (vw - w * dot) * inv_qnorm
            v_quats[g, 1] = (vx - x * dot) * inv_qnorm
            v_quats[g, 2] = (vy - y * dot) * inv_qnorm
            v_quats[g, 3] = (vz - z * dot) * inv_qnorm


@njit(**_OPTS)
def scatter_tile_keys(
    chunk_lo,
    chunk_hi,
    n_chunks,
    rects,
    tile_counts,
    n,
    depth_bits,
    tile_size,
    tiles_x,
    tiles_per_cam,
    cursor,
    keys,
) -> None:
    """Writes each slot's key (float32 depth bits << 32 | g) at its chunk's cursor for its tile.

    Chunks are those of `project_forward`'s histogram (fixed ranges of Gaussians, all cameras each). cursor
    [n_chunks, n_tiles] starts at each chunk's first position inside each tile's segment, so chunks scatter without
    atomics and a tile's keys (all of one camera) arrive in increasing Gaussian index.
    """
    n_cams = tile_counts.shape[0] // n
    shift = _tile_shift(tile_size)
    for chunk in range(chunk_lo, chunk_hi):
        lo, hi = _chunk_bounds(chunk, n_chunks, n)
        chunk_cursor = cursor[chunk]
        for g in range(lo, hi):
            for c in range(n_cams):
                cg = c * n + g
                if tile_counts[cg] == 0:
                    continue
                key = (depth_bits[cg] << 32) | g
                base = c * tiles_per_cam
                tx0, tx1 = _tile_of(rects[cg, 0], tile_size, shift), _tile_of(rects[cg, 1], tile_size, shift)
                ty0, ty1 = _tile_of(rects[cg, 2], tile_size, shift), _tile_of(rects[cg, 3], tile_size, shift)
                if tile_counts[cg] == 1:
                    t = base + ty0 * tiles_x + tx0
                    keys[chunk_cursor[t]] = key
                    chunk_cursor[t] += 1
                    continue
                for ty in range(ty0, ty1 + 1):
                    for tx in range(tx0, tx1 + 1):
                        t = base + ty * tiles_x + tx
                        keys[chunk_cursor[t]] = key
                        chunk_cursor[t] += 1


# Below this many keys a tile's keys are insertion-sorted; above, radix-sorted by their depth bits.
_RADIX_MIN_KEYS = 48


@njit(inline="always", **_OPTS)
def _sort_by_depth_bits(segment, tmp, counts) -> None:
    """Stable LSD radix sort of segment's int64 keys by their upper 32 bits (float32 depth), 8 bits a pass.

    Bytes that all keys share are skipped (a tile's depths span a narrow range, so the top byte usually
    is). tmp [>= len(segment)] int64 and counts [256] int64 are scratch.
    """
    m = segment.shape[0]
    src, dst = segment, tmp[:m]
    in_tmp = False
    for shift in range(32, 64, 8):
        counts[:] = 0
        for i in range(m):
            counts[(src[i] >> shift) & 0xFF] += 1
        if counts[(src[0] >> shift) & 0xFF] == m:
            continue
        total = 0
        for b in range(256):
            c = counts[b]
            counts[b] = total
            total += c
        for i in range(m):
            b = (src[i] >> shift) & 0xFF
            dst[counts[b]] = src[i]
            counts[b] += 1
        src, dst = dst, src
        in_tmp = not in_tmp
    if in_tmp:
        segment[:] = src


@njit(inline="always", **_OPTS)
def _sort_tile(segment, depths, cam_base, tmp, counts) -> None:
    """Sorts one tile's keys (float32 depth bits << 32 | g, all of one camera) by depth, then Gaussian index.

    Depths are positive, so the bits order like the values. The keys arrive in index order
    (`scatter_tile_keys`), so a stable sort by the depth bits alone leaves equal depths in index order: the
    order of sorting the whole int64 keys, in a few radix passes instead of a comparison sort (measured:
    benchmarks/results/profile.md). Runs whose float32 depths tie are then re-sorted by the float64 depths
    [C * N] (the camera's start at cam_base), since float32 rounding merges depths that differ and the order of
    overlapping splats changes the image. tmp and counts are `_sort_by_depth_bits`'s scratch.
    """
    if segment.shape[0] >= _RADIX_MIN_KEYS:
        _sort_by_depth_bits(segment, tmp, counts)
    else:
        for i in range(1, segment.shape[0]):
            key = segment[i]
            m = i
            while m > 0 and segment[m - 1] > key:
                segment[m] = segment[m - 1]
                m -= 1
            segment[m] = key
    run = 0
    for k in range(1, segment.shape[0] + 1):
        if k < segment.shape[0] and segment[k] >> 32 == segment[run] >> 32:
            continue
        # Stable insertion sort of the run segment[run:k] (already in index order) by float64 depth.
        for i in range(run + 1, k):
            key = segment[i]
            depth = depths[cam_base + (key & _KEY_INDEX_MASK)]
            m = i
            while m > run and depths[cam_base + (segment[m - 1] & _KEY_INDEX_MASK)] > depth:
                segment[m] = segment[m - 1]
                m -= 1
            segment[m] = key
        run = k


@njit(**_OPTS)
def tile_slots(
    lo,
    hi,
    tile_offsets,
    keys,
    depths,
    n,
    tile_size,
    tiles_x,
    tiles_per_cam,
    rects,
    slot_offsets,
    means2d,
    conics,
    opacities,
    two_logs,
    colors,
    slot_f,
    slot_i,
    slot_c,
    slot_at,
    slot_areas,
) -> None:
    """Sorts tiles lo..hi-1 front to back (`_sort_tile`) and fills their slots' records.

    Tile t owns keys[tile_offsets[t]:tile_offsets[t + 1]] and the slots k of that range. Per slot k of pair
    cg = c * N + g: the float (SF_*) and int (SI_*) records, its colour row slot_c[k] = colors[c, g]
    (colors [C, N, D], or [1, N, D] shared by the cameras), the pixel count slot_areas[k] of the slot's rect, and
    slot_at[s] = k. Compositing then reads a tile's splats front to back from consecutive rows instead of
    gathering them from the whole model, where it would wait on cache misses.
    s = slot_offsets[cg] + (the tile's row-major place in the pair's tile rectangle) numbers the slots
    pair-major, so that per-pair sums over slots read slot_at[slot_offsets[cg]:slot_offsets[cg + 1]].
    """
    longest = 0
    for t in range(lo, hi):
        longest = max(longest, tile_offsets[t + 1] - tile_offsets[t])
    tmp = np.empty(longest, np.int64)
    counts = np.empty(256, np.int64)
    shared = colors.shape[0] == 1
    shift = _tile_shift(tile_size)
    depth = colors.shape[2]
    flat_means2d, flat_conics, flat_rects = means2d.reshape(-1), conics.reshape(-1), rects.reshape(-1)
    flat_colors = colors.reshape(-1)
    for t in range(lo, hi):
        c = t // tiles_per_cam
        cam_base = c * n
        _sort_tile(keys[tile_offsets[t] : tile_offsets[t + 1]], depths, cam_base, tmp, counts)
        local = t - c * tiles_per_cam
        ty = local // tiles_x
        tx = local - ty * tiles_x
        x0 = tx * tile_size
        y0 = ty * tile_size
        color_cam = 0 if shared else c
        for k in range(tile_offsets[t], tile_offsets[t + 1]):
            if k + _PREFETCH_AHEAD < tile_offsets[t + 1]:
                g_ahead = keys[k + _PREFETCH_AHEAD] & _KEY_INDEX_MASK
                pair_ahead = cam_base + g_ahead
                _prefetch(flat_means2d, 2 * pair_ahead)
                _prefetch(flat_conics, 3 * pair_ahead)
                _prefetch(flat_rects, 4 * pair_ahead)
                _prefetch(slot_offsets, pair_ahead)
                _prefetch(opacities, g_ahead)
                _prefetch(two_logs, g_ahead)
                _prefetch(flat_colors, depth * (color_cam * n + g_ahead))
            g = keys[k] & _KEY_INDEX_MASK
            cg = cam_base + g
            slot_f[k, SF_MX] = means2d[c, g, 0]
            slot_f[k, SF_MY] = means2d[c, g, 1]
            slot_f[k, SF_A] = conics[c, g, 0]
            slot_f[k, SF_B] = conics[c, g, 1]
            slot_f[k, SF_C] = conics[c, g, 2]
            slot_f[k, SF_OPACITY] = opacities[g]
            slot_f[k, SF_LIMIT] = 0.5 * two_logs[g] + _SIGMA_MARGIN
            for d in range(colors.shape[2]):
                slot_c[k, d] = colors[color_cam, g, d]
            u_lo, u_hi, v_lo, v_hi = rects[cg, 0], rects[cg, 1], rects[cg, 2], rects[cg, 3]
            slot_i[k, SI_U_LO] = max(u_lo, x0)
            slot_i[k, SI_U_HI] = min(u_hi, x0 + tile_size - 1)
            slot_i[k, SI_V_LO] = max(v_lo, y0)
            slot_i[k, SI_V_HI] = min(v_hi, y0 + tile_size - 1)
            slot_areas[k] = (slot_i[k, SI_U_HI] - slot_i[k, SI_U_LO] + 1) * (slot_i[k, SI_V_HI] - slot_i[k, SI_V_LO] + 1)
            tx0 = _tile_of(u_lo, tile_size, shift)
            tiles_w = _tile_of(u_hi, tile_size, shift) - tx0 + 1
            slot_at[slot_offsets[cg] + (ty - _tile_of(v_lo, tile_size, shift)) * tiles_w + tx - tx0] = k


@njit(**_OPTS)
def balance_tiles(tile_offsets, n_bins):
    """Greedy longest-first assignment of tiles to n_bins work bins by intersection count.

    Returns (work [n_tiles] tile ids grouped by bin, work_offsets [n_bins + 1]). Bins of about equal
    cost let threads share the work evenly; contiguous runs of tiles would not, since the object's
    tiles carry nearly all of it.
    """
    n_tiles = tile_offsets.shape[0] - 1
    cost = np.empty(n_tiles, np.int64)
    for t in range(n_tiles):
        cost[t] = tile_offsets[t + 1] - tile_offsets[t] + 1
    order = np.argsort(-cost, kind="mergesort")
    load = np.zeros(n_bins, np.int64)
    owner = np.empty(n_tiles, np.int64)
    size = np.zeros(n_bins + 1, np.int64)
    for t in order:
        best = 0
        for k in range(1, n_bins):
            if load[k] < load[best]:
                best = k
        owner[t] = best
        load[best] += cost[t]
        size[best + 1] += 1
    work_offsets = np.cumsum(size)
    fill = work_offsets[:-1].copy()
    work = np.empty(n_tiles, np.int64)
    for t in order:
        work[fill[owner[t]]] = t
        fill[owner[t]] += 1
    return work, work_offsets


@njit(inline="always", **_OPTS)
def _tile_geometry(tile, tiles_x, tiles_per_cam, tile_size, width, height):
    """(camera, first and last pixel column and row) of a global tile id."""
    c = tile // tiles_per_cam
    local = tile - c * tiles_per_cam
    ty = local // tiles_x
    tx = local - ty * tiles_x
    x0 = tx * tile_size
    y0 = ty * tile_size
    return c, x0, y0, min(width, x0 + tile_size) - 1, min(height, y0 + tile_size) - 1


@njit(inline="always", **_OPTS)
def _ellipse_pixels(slot_f, slot_i, k, x0, y0, live, buf_p, buf_sigma) -> int:
    """Lists the live pixels of slot k's tile (origin x0, y0) where its splat may reach alpha >= 1/255.

    That is sigma <= ln(255 opacity), the ellipse inside the slot's pixel rect, and the pixel's bit
    set in its row's mask live [tile rows] (bit u for column x0 + u). Rows without a live pixel in the
    rect are skipped; inside a row every rect pixel is evaluated, LIST_LANES at a time, and packed
    (`_list_lanes`): with the same trip count on every row this beats solving each row's span, whose
    square root and unpredictable loop bounds cost more than the rect pixels they skip (benchmarks/results/rasterizer.md).
    Writes the tile-local pixel index and sigma of each listed pixel to buf_p and buf_sigma (room for
    the rect and LIST_LANES more); returns how many there are.
    """
    mx, my = slot_f[k, SF_MX], slot_f[k, SF_MY]
    a, b, cc = slot_f[k, SF_A], slot_f[k, SF_B], slot_f[k, SF_C]
    limit = slot_f[k, SF_LIMIT]
    col_lo = slot_i[k, SI_U_LO]
    col_hi = slot_i[k, SI_U_HI]
    box = _row_mask(col_hi - col_lo + 1) << (col_lo - x0)
    m = 0
    for py in range(slot_i[k, SI_V_LO], slot_i[k, SI_V_HI] + 1):
        bits = live[py - y0] & box
        if bits == 0:
            continue
        dy = py + 0.5 - my
        row = ((py - y0) << _ROW_SHIFT) - x0
        half_c_dy2 = 0.5 * cc * dy * dy
        for px0 in range(col_lo, col_hi + 1, LIST_LANES):
            m = _list_lanes(buf_p, buf_sigma, m, px0, row + px0, bits, px0 - x0, mx, dy, a, b, half_c_dy2, limit)
    return m


@njit(inline="always", **_OPTS)
def _row_mask(count: int) -> int:
    """Bits 0..count-1 set (count <= MAX_TILE_SIZE)."""
    return -1 if count >= 64 else (1 << count) - 1


@njit(inline="always", **_OPTS)
def _clear_live(live, p: int) -> None:
    """Clears tile-local pixel p's bit in the row masks."""
    live[p >> _ROW_SHIFT] &= ~(1 << (p & (MAX_TILE_SIZE - 1)))


@njit(inline="always", **_OPTS)
def _exp_neg(sigma, out, m) -> None:
    """out[:m] = exp(-sigma[:m]) to ~1e-15 relative for sigma in [0, 8], branch-free so it vectorises.

    libm's exp is a scalar call and costs about as much as the rest of the compositing. Here
    exp(-s) = (e^-0.5 exp(-y))^8 with y = s / 8 - 0.5 in [-0.5, 0.5] (degree-13 Taylor, 7e-16).
    sigma < 0 gives 1 and sigma > 8 gives e^-8, which no opacity <= 1 lifts to 1/255: callers test
    sigma < 0 themselves and the alpha threshold rejects the rest, as exact exp would.
    """
    for i in range(m):
        y = min(max(sigma[i], 0.0), 8.0) * 0.125 - 0.5
        p = 1.0 / 6227020800.0
        p = p * -y + 1.0 / 479001600.0
        p = p * -y + 1.0 / 39916800.0
        p = p * -y + 1.0 / 3628800.0
        p = p * -y + 1.0 / 362880.0
        p = p * -y + 1.0 / 40320.0
        p = p * -y + 1.0 / 5040.0
        p = p * -y + 1.0 / 720.0
        p = p * -y + 1.0 / 120.0
        p = p * -y + 1.0 / 24.0
        p = p * -y + 1.0 / 6.0
        p = p * -y + 0.5
        p = p * -y + 1.0
        p = (p * -y + 1.0) * _EXP_MINUS_HALF
        p = p * p
        p = p * p
        out[i] = p * p


@njit(fastmath=_FUSED, **_OPTS)
def rasterize_forward(
    bin_lo,
    bin_hi,
    slot_f,
    slot_c,
    slot_i,
    tile_offsets,
    work,
    work_offsets,
    tile_size,
    tiles_x,
    backgrounds,
    width,
    height,
    pair_offsets,
    out_colors,
    out_transmittance,
    render_colors,
    render_alphas,
    slot_starts,
    slot_counts,
    pair_px,
    pair_vis,
) -> None:
    """Front-to-back alpha compositing, one tile at a time, splat-major inside a tile.

    Each pixel sees its splats in the tile's depth order, exactly as a per-pixel loop would; walking
    splats in the outer loop lets each visit only the pixels inside its own ellipse and batch their
    exponentials. Pixels whose transmittance has terminated leave their row's live mask, so splats
    over saturated pixels cost a few mask tests. Writes out_colors [C, H, W, D] and out_transmittance
    [C, H, W] (final T) in the tiles some slot covers, the same colours and alpha = 1 - T in the caller's dtype (render_colors
    [C, H, W, D], render_alphas [C, H, W], so that no cast follows), slot_counts [n_isect] (pixels each slot shaded) and, for the backward, each
    shaded pixel of slot k at slot_starts[k] + i (i < slot_counts[k]): pair_px uint16 (tile-local p) and
    pair_vis (exp(-sigma)). A tile's pairs are packed from the room pair_offsets [n_isect + 1] gives its
    first slot (room for every slot's whole pixel rect), so the backward reads them densely.
    """
    depth = slot_c.shape[1]
    # RGB (Stage II's renders) keeps a slot's colour and its gradient in registers (benchmarks/results/rasterizer.md).
    rgb = depth == 3
    tiles_per_cam = tiles_x * ((height + tile_size - 1) // tile_size)
    n_px = tile_size << _ROW_SHIFT
    n_list = tile_size * tile_size
    for bin_ in range(bin_lo, bin_hi):
        trans = np.empty(n_px)
        acc = np.empty((n_px, depth))
        live = np.empty(tile_size, np.int64)
        buf_p = np.empty(n_list + LIST_LANES, np.int64)
        buf_sigma = np.empty(n_list + LIST_LANES)
        buf_vis = np.empty(n_list)
        for w in range(work_offsets[bin_], work_offsets[bin_ + 1]):
            tile = work[w]
            c, x0, y0, x1, y1 = _tile_geometry(tile, tiles_x, tiles_per_cam, tile_size, width, height)
            if tile_offsets[tile] == tile_offsets[tile + 1]:
                # Nothing covers the tile (most of an image whose object is small): background, T = 1. Only the
                # returned images are written; the backward skips the tile, so its float64 state would be written and
                # never read (benchmarks/results/rasterizer.md).
                for py in range(y0, y1 + 1):
                    for px in range(x0, x1 + 1):
                        for d in range(depth):
                            render_colors[c, py, px, d] = backgrounds[c, d]
                        render_alphas[c, py, px] = 0.0
                continue
            used = (y1 - y0 + 1) << _ROW_SHIFT
            trans[:used] = 1.0
            acc[:used] = 0.0
            live[:] = _row_mask(x1 - x0 + 1)
            n_live = (x1 - x0 + 1) * (y1 - y0 + 1)
            out = pair_offsets[tile_offsets[tile]]
            for k in range(tile_offsets[tile], tile_offsets[tile + 1]):
                slot_starts[k] = out
                slot_counts[k] = 0
                if n_live == 0:
                    continue
                m = _ellipse_pixels(slot_f, slot_i, k, x0, y0, live, buf_p, buf_sigma)
                if m == 0:
                    continue
                _exp_neg(buf_sigma, buf_vis, m)
                opacity = slot_f[k, SF_OPACITY]
                c0, c1, c2 = (slot_c[k, 0], slot_c[k, 1], slot_c[k, 2]) if rgb else (0.0, 0.0, 0.0)
                for i in range(m):
                    if buf_sigma[i] < 0.0:
                        continue
                    alpha = min(ALPHA_MAX, opacity * buf_vis[i])
                    if alpha < ALPHA_THRESHOLD:
                        continue
                    p = buf_p[i]
                    next_t = trans[p] * (1.0 - alpha)
                    if next_t <= TRANSMITTANCE_MIN:
                        _clear_live(live, p)
                        n_live -= 1
                        continue
                    weight = alpha * trans[p]
                    if rgb:
                        acc[p, 0] += weight * c0
                        acc[p, 1] += weight * c1
                        acc[p, 2] += weight * c2
                    else:
                        for d in range(depth):
                            acc[p, d] += weight * slot_c[k, d]
                    trans[p] = next_t
                    pair_px[out] = p
                    pair_vis[out] = buf_vis[i]
                    out += 1
                slot_counts[k] = out - slot_starts[k]
            for py in range(y0, y1 + 1):
                for px in range(x0, x1 + 1):
                    p = ((py - y0) << _ROW_SHIFT) + (px - x0)
                    for d in range(depth):
                        value = acc[p, d] + trans[p] * backgrounds[c, d]
                        out_colors[c, py, px, d] = value
                        render_colors[c, py, px, d] = value
                    out_transmittance[c, py, px] = trans[p]
                    render_alphas[c, py, px] = 1.0 - trans[p]


@njit(fastmath=_FUSED, **_OPTS)
def rasterize_backward(
    bin_lo,
    bin_hi,
    slot_f,
    slot_c,
    slot_i,
    tile_offsets,
    work,
    work_offsets,
    tile_size,
    tiles_x,
    backgrounds,
    width,
    height,
    out_colors,
    transmittance,
    slot_starts,
    slot_counts,
    pair_px,
    pair_vis,
    v_out_colors,
    v_out_alphas,
    slot_grads,
) -> None:
    """VJP of `rasterize_forward`: each tile's shaded pixels again, front to back, as the forward listed them.

    The forward's out_colors [C, H, W, D], transmittance [C, H, W], slot_starts, slot_counts, pair_px and pair_vis
    come in, with v_out_colors [C, H, W, D] and v_out_alphas [C, H, W] (in the caller's dtype). T is recomputed by the same
    products as in the forward (no division by 1 - alpha); the colour behind a splat is the pixel's
    accumulated colour minus what the splats up to it added. slot_grads [n_isect, 6 + D] receives
    per-slot d/d(mean2d x, y, conic a, b, c, opacity, colour...).
    Any colour depth (Stage I's silhouettes have none); `rasterize_backward_rgb` computes the same for D = 3.
    """
    depth = slot_c.shape[1]
    tiles_per_cam = tiles_x * ((height + tile_size - 1) // tile_size)
    n_px = tile_size << _ROW_SHIFT
    for bin_ in range(bin_lo, bin_hi):
        trans = np.empty(n_px)
        behind = np.empty((n_px, depth))
        v_px = np.empty((n_px, depth))
        v_t_term = np.empty(n_px)
        v_color = np.empty(depth)
        for w in range(work_offsets[bin_], work_offsets[bin_ + 1]):
            tile = work[w]
            if tile_offsets[tile] == tile_offsets[tile + 1]:
                continue
            c, x0, y0, x1, y1 = _tile_geometry(tile, tiles_x, tiles_per_cam, tile_size, width, height)
            _pixel_state(
                c, x0, y0, x1, y1, backgrounds, out_colors, transmittance, v_out_colors, v_out_alphas, trans, behind, v_px, v_t_term
            )
            for k in range(tile_offsets[tile], tile_offsets[tile + 1]):
                if slot_counts[k] == 0:
                    slot_grads[k, :] = 0.0
                    continue
                _slot_backward(
                    k,
                    slot_f,
                    slot_c,
                    x0,
                    y0,
                    np.uint64(slot_starts[k]),
                    np.uint64(slot_counts[k]),
                    pair_px,
                    pair_vis,
                    trans,
                    behind,
                    v_px,
                    v_t_term,
                    v_color,
                    slot_grads,
                )


@njit(fastmath=_FUSED, **_OPTS)
def rasterize_backward_rgb(
    bin_lo,
    bin_hi,
    slot_f,
    slot_c,
    slot_i,
    tile_offsets,
    work,
    work_offsets,
    tile_size,
    tiles_x,
    backgrounds,
    width,
    height,
    out_colors,
    transmittance,
    slot_starts,
    slot_counts,
    pair_px,
    pair_vis,
    v_out_colors,
    v_out_alphas,
    slot_grads,
) -> None:
    """`rasterize_backward` for three colour channels (Stage II's renders), to the bit.

    A kernel of its own: with both loops in one, LLVM laid out the registers of the colourless loop worse
    (benchmarks/results/rasterizer.md).
    """
    tiles_per_cam = tiles_x * ((height + tile_size - 1) // tile_size)
    n_px = tile_size << _ROW_SHIFT
    for bin_ in range(bin_lo, bin_hi):
        trans = np.empty(n_px)
        behind = np.empty((n_px, 3))
        v_px = np.empty((n_px, 3))
        v_t_term = np.empty(n_px)
        v_alphas = np.empty(tile_size * tile_size)
        for w in range(work_offsets[bin_], work_offsets[bin_ + 1]):
            tile = work[w]
            if tile_offsets[tile] == tile_offsets[tile + 1]:
                continue
            c, x0, y0, x1, y1 = _tile_geometry(tile, tiles_x, tiles_per_cam, tile_size, width, height)
            _pixel_state(
                c, x0, y0, x1, y1, backgrounds, out_colors, transmittance, v_out_colors, v_out_alphas, trans, behind, v_px, v_t_term
            )
            for k in range(tile_offsets[tile], tile_offsets[tile + 1]):
                if slot_counts[k] == 0:
                    slot_grads[k, :] = 0.0
                    continue
                start = np.uint64(slot_starts[k])
                count = np.uint64(slot_counts[k])
                _composite_backward_rgb(
                    k, slot_f, slot_c, start, count, pair_px, pair_vis, trans, behind, v_px, v_t_term, v_alphas, slot_grads
                )
                _geometry_backward(k, slot_f, x0, y0, start, count, pair_px, pair_vis, v_alphas, slot_grads)


@njit(inline="always", **_OPTS)
def _pixel_state(
    c, x0, y0, x1, y1, backgrounds, out_colors, transmittance, v_out_colors, v_out_alphas, trans, behind, v_px, v_t_term
) -> None:
    """A tile's per-pixel state before its first splat (tile-local p): trans = 1, behind [tile px, D] = the colour all
    splats added, v_px [tile px, D] = the colour gradient and v_t_term = T_final * d loss / d T_final."""
    depth = behind.shape[1]
    for py in range(y0, y1 + 1):
        for px in range(x0, x1 + 1):
            p = ((py - y0) << _ROW_SHIFT) + (px - x0)
            t_final = transmittance[c, py, px]
            trans[p] = 1.0
            # alpha = 1 - T and colour += T * background both depend on every splat through
            # T_final; d T_final / d alpha_i = -T_final / (1 - alpha_i).
            v_t = -v_out_alphas[c, py, px]
            for d in range(depth):
                behind[p, d] = out_colors[c, py, px, d] - t_final * backgrounds[c, d]
                v_px[p, d] = v_out_colors[c, py, px, d]
                v_t += backgrounds[c, d] * v_px[p, d]
            v_t_term[p] = t_final * v_t


@njit(inline="always", fastmath=_FUSED, **_OPTS)
def _composite_backward_rgb(
    k, slot_f, slot_c, start, count, pair_px, pair_vis, trans, behind, v_px, v_t_term, v_alphas, slot_grads
) -> None:
    """Slot k's colour gradient (slot_grads[k, 6:9]) and, as it walks the slot's pairs, the pixels' state behind it
    (trans [tile px], behind [tile px, 3]) and d loss / d alpha of each pair whose alpha is not clamped (v_alphas[j] for
    the slot's j-th pair), which `_geometry_backward` reads.

    Two passes over a slot's pairs, this and `_geometry_backward`: in one, its 9 running sums and 12 constants did not fit
    the 16 vector registers of x86-64 without AVX-512 and spilled on every pair (benchmarks/results/rasterizer.md).
    Indices are unsigned so that numba does not wrap negative ones."""
    opacity = slot_f[k, SF_OPACITY]
    c0, c1, c2 = slot_c[k, 0], slot_c[k, 1], slot_c[k, 2]
    v_c0 = 0.0
    v_c1 = 0.0
    v_c2 = 0.0
    for j in range(count):
        i = start + j
        p = pair_px[i]
        raw_alpha = opacity * pair_vis[i]
        alpha = min(ALPHA_MAX, raw_alpha)
        one_minus = 1.0 - alpha
        t_here = trans[p]
        weight = alpha * t_here
        b0 = behind[p, 0] - c0 * weight
        b1 = behind[p, 1] - c1 * weight
        b2 = behind[p, 2] - c2 * weight
        behind[p, 0] = b0
        behind[p, 1] = b1
        behind[p, 2] = b2
        g0, g1, g2 = v_px[p, 0], v_px[p, 1], v_px[p, 2]
        v_c0 += weight * g0
        v_c1 += weight * g1
        v_c2 += weight * g2
        trans[p] = t_here * one_minus
        # Where min() clamps alpha to 0.999 it no longer depends on opacity or sigma.
        if raw_alpha <= ALPHA_MAX:
            inv_one_minus = 1.0 / one_minus
            v_alpha = -inv_one_minus * v_t_term[p]
            v_alpha += (c0 * t_here - b0 * inv_one_minus) * g0
            v_alpha += (c1 * t_here - b1 * inv_one_minus) * g1
            v_alpha += (c2 * t_here - b2 * inv_one_minus) * g2
            v_alphas[j] = v_alpha
    slot_grads[k, 6] = v_c0
    slot_grads[k, 7] = v_c1
    slot_grads[k, 8] = v_c2


@njit(inline="always", fastmath=_FUSED, **_OPTS)
def _geometry_backward(k, slot_f, x0, y0, start, count, pair_px, pair_vis, v_alphas, slot_grads) -> None:
    """Slot k's mean2d, conic and opacity gradients (slot_grads[k, :6]) from `_composite_backward_rgb`'s v_alphas, summed
    in pair order as the one-pass loop summed them."""
    opacity = slot_f[k, SF_OPACITY]
    mx, my = slot_f[k, SF_MX], slot_f[k, SF_MY]
    a, b, cc = slot_f[k, SF_A], slot_f[k, SF_B], slot_f[k, SF_C]
    sums = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    for j in range(count):
        i = start + j
        vis = pair_vis[i]
        raw_alpha = opacity * vis
        if raw_alpha <= ALPHA_MAX:
            sums = _add_geometry(sums, pair_px[i], x0, y0, mx, my, a, b, cc, raw_alpha, vis, v_alphas[j])
    _store_geometry(slot_grads, k, sums)


@njit(inline="always", **_OPTS)
def _store_geometry(slot_grads, k, sums) -> None:
    """slot_grads[k, :6] = sums, element by element (numba's slice assignment from a tuple is slower: benchmarks/results/profile.md)."""
    slot_grads[k, 0], slot_grads[k, 1], slot_grads[k, 2] = sums[0], sums[1], sums[2]
    slot_grads[k, 3], slot_grads[k, 4], slot_grads[k, 5] = sums[3], sums[4], sums[5]


@njit(inline="always", fastmath=_FUSED, **_OPTS)
def _add_geometry(sums, p, x0, y0, mx, my, a, b, cc, raw_alpha, vis, v_alpha):
    """The running sums (d/d mean2d x, y, conic a, b, c, opacity) plus pixel p's share, from its d loss / d alpha."""
    v_mx, v_my, v_a, v_b, v_c, v_opacity = sums
    # The forward's offsets, by the same operations.
    dx = (x0 + (p & (MAX_TILE_SIZE - 1))) + 0.5 - mx
    dy = (y0 + (p >> _ROW_SHIFT)) + 0.5 - my
    v_sigma = -raw_alpha * v_alpha
    v_a += 0.5 * v_sigma * dx * dx
    v_b += v_sigma * dx * dy
    v_c += 0.5 * v_sigma * dy * dy
    v_mx -= v_sigma * (a * dx + b * dy)
    v_my -= v_sigma * (b * dx + cc * dy)
    v_opacity += vis * v_alpha
    return v_mx, v_my, v_a, v_b, v_c, v_opacity


@njit(inline="always", fastmath=_FUSED, **_OPTS)
def _slot_backward(k, slot_f, slot_c, x0, y0, start, count, pair_px, pair_vis, trans, behind, v_px, v_t_term, v_color, slot_grads) -> None:
    """Slot k's whole gradient row for any colour depth (Stage I's silhouettes have none) in one pass over its pairs."""
    depth = slot_c.shape[1]
    opacity = slot_f[k, SF_OPACITY]
    mx, my = slot_f[k, SF_MX], slot_f[k, SF_MY]
    a, b, cc = slot_f[k, SF_A], slot_f[k, SF_B], slot_f[k, SF_C]
    sums = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    v_color[:] = 0.0
    for j in range(count):
        i = start + j
        p = pair_px[i]
        vis = pair_vis[i]
        raw_alpha = opacity * vis
        alpha = min(ALPHA_MAX, raw_alpha)
        one_minus = 1.0 - alpha
        inv_one_minus = 1.0 / one_minus
        t_here = trans[p]
        weight = alpha * t_here
        v_alpha = -inv_one_minus * v_t_term[p]
        for d in range(depth):
            col_d = slot_c[k, d]
            behind[p, d] -= col_d * weight
            v_color[d] += weight * v_px[p, d]
            v_alpha += (col_d * t_here - behind[p, d] * inv_one_minus) * v_px[p, d]
        trans[p] = t_here * one_minus
        # Where min() clamps alpha to 0.999 it no longer depends on opacity or sigma.
        if raw_alpha <= ALPHA_MAX:
            sums = _add_geometry(sums, p, x0, y0, mx, my, a, b, cc, raw_alpha, vis, v_alpha)
    _store_geometry(slot_grads, k, sums)
    for d in range(depth):
        slot_grads[k, 6 + d] = v_color[d]


@njit(**_OPTS)
def sum_slot_gradients(lo, hi, slot_grads, slot_offsets, slot_at, v_means2d, v_conics, v_opacities, v_colors) -> None:
    """Per-pair sums of `rasterize_backward`'s slot_grads [n_isect, 6 + D] over pair cg's slots, in slot order, written
    straight into the inputs' gradient layouts: v_means2d [C * N, 2], v_conics [C * N, 3], v_opacities [C * N],
    v_colors [C * N, D] (contiguous arrays the caller hands to torch, instead of strided copies of one [C * N, 6 + D])."""
    width = slot_grads.shape[1]
    flat_grads = slot_grads.reshape(-1)
    last = slot_offsets[hi]
    for cg in range(lo, hi):
        mx = my = a = b = c = opacity = 0.0
        for d in range(width - N_GRAD_GEOMETRY):
            v_colors[cg, d] = 0.0
        for s in range(slot_offsets[cg], slot_offsets[cg + 1]):
            if s + _PREFETCH_AHEAD < last:
                row = slot_at[s + _PREFETCH_AHEAD] * width
                _prefetch(flat_grads, row)
                _prefetch(flat_grads, row + width - 1)
            k = slot_at[s]
            mx += slot_grads[k, 0]
            my += slot_grads[k, 1]
            a += slot_grads[k, 2]
            b += slot_grads[k, 3]
            c += slot_grads[k, 4]
            opacity += slot_grads[k, 5]
            for d in range(width - N_GRAD_GEOMETRY):
                v_colors[cg, d] += slot_grads[k, N_GRAD_GEOMETRY + d]
        v_means2d[cg, 0] = mx
        v_means2d[cg, 1] = my
        v_conics[cg, 0] = a
        v_conics[cg, 1] = b
        v_conics[cg, 2] = c
        v_opacities[cg] = opacity


@njit(**_OPTS)
def sum_slot_counts(lo, hi, slot_counts, slot_offsets, slot_at, out) -> None:
    """out[cg] = sum of slot_counts over pair cg's slots; out [C * N]."""
    last = slot_offsets[hi]
    for cg in range(lo, hi):
        total = 0
        for s in range(slot_offsets[cg], slot_offsets[cg + 1]):
            if s + _PREFETCH_AHEAD < last:
                _prefetch(slot_counts, slot_at[s + _PREFETCH_AHEAD])
            total += slot_counts[slot_at[s]]
        out[cg] = total
