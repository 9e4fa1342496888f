"""The per-texel pass of :class:`service.geometry.normal_map.NormalMapper`, compiled (issue 23).

For each covered texel of a normal map: the vertex rows (T, N) interpolated with the texel's
barycentric weights over its triangle's corners, the surface gradient ``g = Ku ∂h/∂u +
Kv ∂h/∂v`` of the triangle's operators (1), the texel frame's projections of g and the unit
normal ``(x, y, 1) / |(x, y, 1)|`` written straight into the output map
(:mod:`service.geometry.normal_map`'s module notes). As NumPy passes over blocks of texels
this was six sparse products, a gather of (Ku, Kv), about 40 elementwise passes over (3,b)
temporaries and a scatter of the results (the level-1 sample actor's 1024² map, 715k
covered texels: about 30 of 45 ms per map); here each texel is read and written once, in a
Numba kernel over texel ranges ``[lo, hi)`` (:func:`service.geometry.ranges.run`).

The texel's finite differences of the map (∂h/∂u, ∂h/∂v: central, one-sided or zero by the
texel's stencil bits, :func:`service.geometry.normal_map.stencil_codes`) are read in the same
loop from the map itself (its neighbours along the row and the column: near-sequential
loads), instead of two difference images, gathers and patches per axis before the pass
(level-1 1024² map: 5.6 ms of cProfile gone, the pass ≈ 0.5 ms longer). The per-triangle
operators (1) are a kernel of their own here (:func:`triangle_operators`).

The kernel runs over blocks of :data:`BLOCK` texels in three loops, so that the arithmetic
is done on SIMD vectors of texels: (a) the gathers — the corners' (T, N) and the triangle's
(Ku, Kv) — with the interpolation and gradient into nine contiguous float32 rows
(structure of arrays), (b) the frame, projections and normalization (three square roots
and three divisions per texel, no branch: the clamp is a select) over those rows, which
LLVM vectorizes (``vsqrtps``/``vdivps`` on 8 texels at once), (c) the results written to
their texels. Measured on the ICT rig's 814k covered texels at 1024² (one core of the 2-vCPU
Xeon VM, the two kernels alternating in one process, load 2): one scalar loop (gather,
arithmetic and store per texel) 12.3 ms, blocked 7.9 ms, of which (a) is 5.9 and (b)-(c)
2.5. Measured and not kept: per-triangle rows of the corners' (T, N) and (Ku, Kv) gathered
once per frame and read per texel (9.2 ms), and vertex-interleaved (T, N) interpolated as
8-wide vectors (11.5 ms): (a) is bound by its loads either way.

The same float32 operations in the same order as the NumPy passes (compiled without
fast-math: nothing reassociated or contracted; the interpolation sums the three corners in
order from 0, as SciPy's CSR product did), so the maps are the NumPy path's bit for bit
(tests/geometry/test_normal_map.py, tests/geometry/test_normal_texels.py). NumPy's error
model: IEEE division without a zero test per division (the Python model's tests cost the
pass 18 → 14 ms on the level-1 map). Numba is imported here: the mapper imports this module
when it is built, i.e. where a model is built, never by ``facesynth serve``'s start.
"""

from __future__ import annotations

import numpy as np
from numba import njit, types, uint64
from numba.extending import overload

from service.geometry.half_kernel import binary16

#: texels per block of :func:`normal_texels` (its two work arrays, 12 rows of BLOCK float32,
#: stay in the L1 cache; 64-1024 measured within 0.6 ms of each other)
BLOCK = 128
#: bits of a texel's stencil code (:func:`stencil_codes`): the neighbour along +x (+u), −x,
#: +y (−v), −y is a covered texel of the same chart
U_FWD, U_BWD, V_FWD, V_BWD = 1, 2, 4, 8


@njit(nogil=True, cache=True, error_model="numpy", inline="always")
def _interpolate(TN, r, v0, v1, v2, w0, w1, w2):
    """Row r of TN (6,n) at a texel: ``0 + w0 TN[r,v0] + w1 TN[r,v1] + w2 TN[r,v2]`` summed
    in that order (SciPy's CSR row sum)."""
    s = np.float32(0) + w0 * TN[r, v0]
    s += w1 * TN[r, v1]
    s += w2 * TN[r, v2]
    return s


@njit(nogil=True, cache=True, error_model="numpy", inline="always")
def _unit_normal(t0, t1, t2, n0, n1, n2, g0, g1, g2, eps):
    """(x, y, z) of the unit normal ``(x', y', 1) / |(x', y', 1)|`` of a texel with the
    interpolated T, N and gradient g: ``X = T × N``, ``Z = X × N``, ``x' = Z·g / |Z|``,
    ``y' = X·g / |X|`` (the squared norms clamped below at ``eps``; NaN kept)."""
    one = np.float32(1)
    x0 = t1 * n2 - t2 * n1                     # X = T × N
    x1 = t2 * n0 - t0 * n2
    x2 = t0 * n1 - t1 * n0
    z0 = x1 * n2 - x2 * n1                     # Z = X × N
    z1 = x2 * n0 - x0 * n2
    z2 = x0 * n1 - x1 * n0
    zz = z0 * z0 + z1 * z1 + z2 * z2
    xx = x0 * x0 + x1 * x1 + x2 * x2
    x = z0 * g0 + z1 * g1 + z2 * g2
    x /= np.sqrt(zz if (zz > eps or zz != zz) else eps)
    y = x0 * g0 + x1 * g1 + x2 * g2
    y /= np.sqrt(xx if (xx > eps or xx != xx) else eps)
    r = x * x
    r += y * y
    r += one
    r = one / np.sqrt(r)
    return x * r, y * r, r


@njit(nogil=True, cache=True, error_model="numpy", inline="always")
def _difference(hf, p, step, code, fwd, bwd, scales):
    """∂h/∂u or ∂h/∂v (float32) at the flat texel p of the map hf (H·W,): ``h[p + step] −
    h[p − step]`` with each side replaced by p itself where its bit of ``code`` (``fwd``,
    ``bwd``) is clear, in hf's dtype, rounded to float32 and times ``scales[count]`` (count the
    usable sides: central, one-sided, or 0)."""
    f = uint64(1) if code & fwd else uint64(0)
    b = uint64(1) if code & bwd else uint64(0)
    d = np.float32(hf[p + f * step] - hf[p - b * step])
    return d * scales[f + b]


@njit(nogil=True, cache=True, error_model="numpy")
def normal_texels(lo, hi, texel, triangle, lam, corners, code, scales, width, hf, K, TN, eps, out):
    """Texels [lo, hi): ``out[texel[i]]`` (H·W,3) float32 = the unit tangent-space normal of
    covered texel i, from its triangle ``triangle[i]`` (a column of the operators K (6,mu)
    float32, rows Ku, Kv), its barycentric weights ``lam`` (N,3) float32 on the vertices
    ``corners`` (N,3), the map's finite differences (:func:`_difference` of hf (H·W,) with
    the texel's stencil bits ``code[i]`` and the scales (2,3) float32 of u and v; ``width``
    W the step of a row) and the vertex rows ``TN`` (6,n) float32 (T, N); ``eps`` the clamp
    of |T×N|² and |Z|² (FRAME_DEGENERATE). In blocks of :data:`BLOCK` texels (module
    docstring). ``out`` (H·W,3) uint16 instead takes the normals as float16 bits
    (:func:`service.geometry.half_kernel.binary16`: NumPy's ``astype(np.float16)`` of the
    float32 normals bit for bit), rounded in the block's last loop."""
    rows = np.empty((9, BLOCK), np.float32)        # t0 t1 t2 n0 n1 n2 g0 g1 g2 of the block
    res = np.empty((3, BLOCK), np.float32)
    block = _block_of(out, res)                    # the block as out holds it
    su, sv = scales[0], scales[1]
    one, w = uint64(1), uint64(width)
    for s in range(uint64(lo), uint64(hi), uint64(BLOCK)):
        n = min(uint64(BLOCK), uint64(hi) - s)
        for j in range(n):                         # (a) gathers, interpolation, gradient
            i = s + j
            p = uint64(texel[i])
            c = code[i]
            a = _difference(hf, p, one, c, U_FWD, U_BWD, su)
            b = _difference(hf, p, w, c, V_FWD, V_BWD, sv)
            q = triangle[i]
            g0 = K[0, q] * a
            g1 = K[1, q] * a
            g2 = K[2, q] * a
            g0 += K[3, q] * b
            g1 += K[4, q] * b
            g2 += K[5, q] * b
            v0, v1, v2 = corners[i, 0], corners[i, 1], corners[i, 2]
            w0, w1, w2 = lam[i, 0], lam[i, 1], lam[i, 2]
            rows[0, j] = _interpolate(TN, 0, v0, v1, v2, w0, w1, w2)
            rows[1, j] = _interpolate(TN, 1, v0, v1, v2, w0, w1, w2)
            rows[2, j] = _interpolate(TN, 2, v0, v1, v2, w0, w1, w2)
            rows[3, j] = _interpolate(TN, 3, v0, v1, v2, w0, w1, w2)
            rows[4, j] = _interpolate(TN, 4, v0, v1, v2, w0, w1, w2)
            rows[5, j] = _interpolate(TN, 5, v0, v1, v2, w0, w1, w2)
            rows[6, j] = g0
            rows[7, j] = g1
            rows[8, j] = g2
        for j in range(n):                         # (b) vectorized over the block
            res[0, j], res[1, j], res[2, j] = _unit_normal(rows[0, j], rows[1, j], rows[2, j], rows[3, j],
                                                           rows[4, j], rows[5, j], rows[6, j], rows[7, j],
                                                           rows[8, j], eps)
        _round(res, block, n)                      # (b') float16 bits, vectorized too
        for j in range(n):                         # (c) into the map
            p = texel[s + j]
            out[p, 0] = block[0, j]
            out[p, 1] = block[1, j]
            out[p, 2] = block[2, j]


def _block_of(out, res):
    """The (3, BLOCK) array a block's normals are written from: ``res`` itself for a float32
    ``out``, a uint16 one for float16 bits. Resolved by out's type at compile time."""


def _round(res, block, n):
    """Columns [0, n) of the float32 block ``res`` into ``block`` as float16 bits
    (:func:`~service.geometry.half_kernel.binary16`); nothing where ``block`` is res."""


@overload(_block_of)
def _block_of_type(out, res):
    if out.dtype == types.uint16:
        return lambda out, res: np.empty((3, BLOCK), np.uint16)
    return lambda out, res: res


@overload(_round)
def _round_type(res, block, n):
    if block.dtype != types.uint16:
        return lambda res, block, n: None

    def rounded(res, block, n):
        bits = res.view(np.uint32)
        for c in range(3):
            for j in range(n):
                block[c, j] = binary16(bits[c, j], res[c, j])
    return rounded


#: the normal of a texel without a gradient, (0, 0, 1), as float32 and as float16 bits
FLAT = np.float32([0, 0, 1])
FLAT_HALF = np.uint16([0, 0, 0x3C00])


@njit(nogil=True, cache=True, error_model="numpy")
def flat_runs(lo, hi, runs, out, flat):
    """Runs [lo, hi) of uncovered texels: ``out[p] = flat`` (H·W,3) for ``runs[r, 0] ≤ p <
    runs[r, 1]``: :data:`FLAT` for a float32 map, :data:`FLAT_HALF` for one of float16 bits."""
    for r in range(uint64(lo), uint64(hi)):
        for p in range(uint64(runs[r, 0]), uint64(runs[r, 1])):
            out[p, 0] = flat[0]
            out[p, 1] = flat[1]
            out[p, 2] = flat[2]


@njit(nogil=True, cache=True, error_model="numpy", inline="always")
def _cross(a0, a1, a2, b0, b1, b2):
    """``a × b`` of two float32 3-vectors, each component ``a_j b_k`` less ``a_k b_j`` (the
    order of the NumPy passes: the product rounded, then the other subtracted)."""
    c0 = a1 * b2
    c0 -= a2 * b1
    c1 = a2 * b0
    c1 -= a0 * b2
    c2 = a0 * b1
    c2 -= a1 * b0
    return c0, c1, c2


@njit(nogil=True, cache=True, error_model="numpy")
def triangle_operators(lo, hi, edges, used, m, uv_edges, sin2, K):
    """Used triangles [lo, hi): the gradient operators (1) ``K[:, t]`` (6,mu) float32 =
    (Ku, Kv) of triangle ``used[t]``, whose edges e1, e2 are columns ``used[t]`` and
    ``used[t] + m`` of ``edges`` (3,2m) float32, and whose UV edges are ``uv_edges[:, t]``
    (Δu1, Δv1, Δu2, Δv2); zero where ``|e1×e2|² ≤ sin2 |e1|²|e2|²`` (degenerate in 3D).
    The float32 operations in the order of the NumPy passes over (3,mu) rows this replaced
    (tests/geometry/test_normal_map.py pins it against them bit for bit)."""
    for t in range(uint64(lo), uint64(hi)):
        a = uint64(used[t])
        b = a + uint64(m)
        p0, p1, p2 = edges[0, a], edges[1, a], edges[2, a]
        q0, q1, q2 = edges[0, b], edges[1, b], edges[2, b]
        n0, n1, n2 = _cross(p0, p1, p2, q0, q1, q2)                 # n = e1 × e2
        det = n0 * n0 + n1 * n1 + n2 * n2
        inv = np.float32(0)
        if det > sin2 * (p0 * p0 + p1 * p1 + p2 * p2) * (q0 * q0 + q1 * q1 + q2 * q2):
            inv = np.float32(1) / det
        a0, a1, a2 = _cross(q0, q1, q2, n0, n1, n2)                 # a1 = (e2 × n) / |n|²
        a0, a1, a2 = a0 * inv, a1 * inv, a2 * inv
        b0, b1, b2 = _cross(n0, n1, n2, p0, p1, p2)                 # a2 = (n × e1) / |n|²
        b0, b1, b2 = b0 * inv, b1 * inv, b2 * inv
        du1, dv1, du2, dv2 = uv_edges[0, t], uv_edges[1, t], uv_edges[2, t], uv_edges[3, t]
        K[0, t] = a0 * du1 + b0 * du2
        K[1, t] = a1 * du1 + b1 * du2
        K[2, t] = a2 * du1 + b2 * du2
        K[3, t] = a0 * dv1 + b0 * dv2
        K[4, t] = a1 * dv1 + b1 * dv2
        K[5, t] = a2 * dv1 + b2 * dv2
