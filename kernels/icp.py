"""Projective ICP on the Taichi side: association, the tracking terms' linearisation and the 6×6 reduction.

One ICP iteration at one pyramid level is one pass over the source pixels (``PointToPlane.reduce``), with
the tracking terms it is given (``TermPass``; the terms themselves are ``ti_fusion.tracking.terms``):

association (``_target_pixel`` then ``_correspondence``, shared by every kernel here; the reductions run
them as two passes per chunk, see ``_project_chunk``)
    a source pixel is used when its vertex has z > 0 and its normal is non-zero. p′ = R p + t is
    projected with the target intrinsics of the level and rounded to the nearest pixel,
    u = ⌊fx x′/z′ + cx + ½⌋, v = ⌊fy y′/z′ + cy + ½⌋. The pair (p′, q = target vertex at (u, v)) is a
    correspondence only if, in this order (the first failing test is the pixel's status code):
        STATUS_SOURCE_INVALID  6  source vertex z ≤ 0 or source normal zero
        STATUS_BEHIND          2  z′ ≤ 0 (behind the target camera, or on its centre plane)
        STATUS_OUT_OF_IMAGE    1  not 0 ≤ u < W and 0 ≤ v < H
        STATUS_TARGET_INVALID  3  target vertex z ≤ 0 or target normal zero
        STATUS_TOO_FAR         4  not ‖p′ − q‖ < d_thr
        STATUS_NORMAL_ANGLE    5  not angle(R n_p, n_q) < θ, tested as (R n_p)·n_q > cos θ
        STATUS_OK              0  a correspondence (an inlier)

linearisation (each term's per-pixel ``ti.func``, unrolled into the pass at compile time)
    at each correspondence each term gives one row (ok, A, r, w): the 1×6 Jacobian A of its residual r with
    respect to the twist δξ = (ω, v) ROTATION FIRST of the left update T ← exp(δξ) T
    (ti_fusion.geometry.se3_exp; to first order exp(δξ) p′ ≈ p′ + ω × p′ + v), its weight w, and whether the
    pixel has one. The first term is point to plane (r = n_qᵀ (p′ − q), A = [(p′ × n_q)ᵀ, n_qᵀ], robust and
    depth-noise weights: ``ti_fusion.tracking.terms.point_to_plane``), always on; the photometric term
    (``…terms.photometric``) and any other follow. The Gauss–Newton step solves
    (Σ_k λ_k Σ w AᵀA) δξ = −Σ_k λ_k Σ w Aᵀ r over the terms k, λ_1 = 1.

reduction
    per term, the kernel accumulates TERM_SUMS = 29 numbers: the 21 upper-triangle entries of Σ w AᵀA
    (row-major: (0,0), (0,1), …, (0,5), (1,1), …, (5,5)), the 6 entries of Σ w Aᵀ r, Σ r² (unweighted: the
    loss) and its row count; the first term's count is the inlier count, and the 30th number, after it, the
    count of valid source pixels (for the inlier ratio); the other terms' 29 follow (``term_offset``): N_SUMS
    = 30 numbers for the geometry alone, 59 with the photometric term. The pixels are split into
    ``n_chunks`` contiguous runs; one parallel task per run accumulates every term's sums in registers and
    writes them as partial sums to ``partials[chunk, :]``; a second loop of the same kernel (Taichi runs top-level loops
    one after the other) adds the partials into a NumPy array passed as an ndarray argument: one launch
    per iteration, no copy on the CPU. No atomics. In float64 (cpu) the partials are added in one serial
    pass with independent running sums; in float32 (GPU backends) in two more parallel loops, each
    Kahan-compensated: GROUPS threads per sum add a contiguous run of the chunks each, then one thread per
    sum adds the GROUPS group totals. That keeps the float32 path within the stated tolerance of float64,
    and no thread adds more than a few hundred numbers in a row (one thread per sum over all the chunks made
    ICP's iterations more than half of a GPU's kernel time: docs/PERFORMANCE.md, "A fourth H200 lease").
    Every product and sum is in the arithmetic type, AᵀA's included: its off-diagonal entries are sums of
    signed terms that can cancel as well as Aᵀb's, so float32 products for them would miss float64 by
    more than the float32 path's tolerance (docs/KERNELS.md).
    The set of terms is a compile-time choice (``kernels_for``: one ``reduce`` and ``iterate`` per set, the terms'
    functions unrolled with ``ti.static``), and so is each term's ``mode`` (e.g. the robust weight).

solve (``iterate``, float64 backends)
    the same kernel can finish the iteration: after the partials are added, on the calling thread, it
    solves the 6×6 system by Cholesky, applies T ← exp(δξ) T to the pose in ``params`` (in place, so the
    next launch starts there) and appends a record (the sums, the pose before, ‖δξ‖, the outcome).
    ``ti_fusion.tracking.icp`` replays the records through its checks. One launch per iteration and nothing read
    back but a flag: a round trip through NumPy per iteration costs as much as a coarse level's pass.
    The system is the first term's plus each other term's times its weight λ (``params``' term columns, e.g.
    ``icp.color_weight`` for the photometric term); a record holds the other terms' sums from R_TERMS on.

Precision: arithmetic and accumulation are float64 when the backend has it (cpu) and float32 otherwise
(vulkan, cuda), chosen when ``PointToPlane`` is built. Fields stay float32.

Images: the source and target maps are levels of stacked fields (``ti_fusion.kernels.pyramid.Level``: the
H × W image at a first row of its field), passed as the field and, at run time, the first row and size
(``Hs``, ``Ws`` for the source, ``Ht``, ``Wt`` for the target), so that one instance of each kernel serves
every pyramid level; a plain H × W field is the level at its row 0. The source's vertex, normal and
intensity share one layout, as do the target's vertex, normal and intensity gradient.
"""


import math
import os
from typing import NamedTuple

import numpy as np
import taichi as ti

from ti_fusion.backend import SERIAL_BELOW, on_cpu
from ti_fusion.geometry import flatten_pose, unflatten_pose
from ti_fusion.kernels.common import data_oriented, depth_noise_scale
from ti_fusion.kernels.pyramid import as_level

STATUS_OK = 0
# ``_target_pixel``: a target pixel index, or one of these (the first three tests' failures)
NO_TARGET = -1  # outside the target image
SOURCE_INVALID = -2
BEHIND_TARGET = -3  # z′ ≤ 0
STATUS_OUT_OF_IMAGE = 1
STATUS_BEHIND = 2
STATUS_TARGET_INVALID = 3
STATUS_TOO_FAR = 4
STATUS_NORMAL_ANGLE = 5
STATUS_SOURCE_INVALID = 6
STATUS_NAMES = {
    STATUS_OK: "ok",
    STATUS_OUT_OF_IMAGE: "out of image",
    STATUS_BEHIND: "behind the camera",
    STATUS_TARGET_INVALID: "target invalid",
    STATUS_TOO_FAR: "too far",
    STATUS_NORMAL_ANGLE: "normal angle",
    STATUS_SOURCE_INVALID: "source invalid",
}

N_SUMS = 30  # 21 AᵀA + 6 Aᵀb + Σr² + inliers + valid source pixels
SUM_ATB = 21
SUM_R2 = 27
SUM_INLIERS = 28
SUM_SOURCE = 29
UPPER = [(i, j) for i in range(6) for j in range(i, 6)]  # order of the 21 AᵀA entries
# Each tracking term's sums: 21 AᵀA, 6 Aᵀb, Σr² and its count of rows, at ``term_offset(k)`` for the k-th term of a
# pass; the first term's are the first 29 of the 30 above (its count is the inliers), the others' follow the 30.
TERM_SUMS = 29
TERM_R2, TERM_COUNT = 27, 28  # within a term's sums
MAX_TERMS = 4  # terms in one pass: the width of the params array's settings and records
_UPPER_IDX = tuple(np.array(UPPER).T)


def term_offset(k: int) -> int:
    """Where the k-th term's 29 sums start in a pass's sums."""
    return 0 if k == 0 else N_SUMS + TERM_SUMS * (k - 1)


def n_sums(n_terms: int) -> int:
    """The sums of a pass with ``n_terms`` terms: 30, and 29 more for each term after the first."""
    return N_SUMS + TERM_SUMS * (n_terms - 1)


def n_terms_of(sums: np.ndarray) -> int:
    """The number of terms of a pass whose sums (the last axis) these are."""
    return 1 + (np.shape(sums)[-1] - N_SUMS) // TERM_SUMS


def unpack_sums(sums: np.ndarray) -> dict:
    """The 30 reduced numbers as AtA (6×6, symmetric), Atb (6), r2 (Σ r²), inliers and sources."""
    sums = np.asarray(sums, dtype=np.float64)
    AtA = np.zeros((6, 6))
    AtA[_UPPER_IDX] = sums[:21]
    AtA.T[_UPPER_IDX] = sums[:21]
    return {"AtA": AtA, "Atb": sums[SUM_ATB:SUM_ATB + 6].copy(), "r2": float(sums[SUM_R2]),
            "inliers": int(round(sums[SUM_INLIERS])), "sources": int(round(sums[SUM_SOURCE]))}


def unpack_term_sums(sums: np.ndarray, k: int) -> dict | None:
    """The k-th term's sums of a pass as AtA, Atb, r2 and count (None when the pass had fewer terms)."""
    sums = np.asarray(sums, dtype=np.float64)
    if k >= n_terms_of(sums):
        return None
    o = term_offset(k)
    s = unpack_sums(sums[o:o + TERM_SUMS].tolist() + [0.0])
    return {"AtA": s["AtA"], "Atb": s["Atb"], "r2": s["r2"], "count": s["inliers"]}


def combined_system(sums: np.ndarray, weights) -> tuple[np.ndarray, np.ndarray]:
    """(AᵀA, Aᵀb) of the system solved: Σ over the pass's terms of its weight × its system (``weights`` one
    per term, the first term's ignored: it is 1)."""
    AtA, Atb = combined_systems(np.asarray(sums, dtype=np.float64)[None], weights)
    return AtA[0], Atb[0]


def combined_systems(sums: np.ndarray, weights) -> tuple[np.ndarray, np.ndarray]:
    """``combined_system`` of each row of ``sums`` (n × ``n_sums(terms)``): n × 6 × 6, n × 6; a term's weight may
    be an n × 1 array (each row's level's)."""
    sums = np.asarray(sums, dtype=np.float64)
    upper, atb = sums[:, :21], sums[:, SUM_ATB:SUM_ATB + 6]
    for k in range(1, n_terms_of(sums)):  # in the kernel's order: the first term, then each other's λ × its sums
        o = term_offset(k)
        upper = upper + weights[k] * sums[:, o:o + 21]
        atb = atb + weights[k] * sums[:, o + 21:o + 27]
    AtA = np.zeros((sums.shape[0], 6, 6))
    AtA[(slice(None),) + _UPPER_IDX] = upper
    AtA.transpose(0, 2, 1)[(slice(None),) + _UPPER_IDX] = upper
    return AtA, atb.copy()


class Correspondence(NamedTuple):
    """What a term's per-pixel function is given of a correspondence (Taichi values, the arithmetic type):
    source pixel (v, u), p′ = R p + t, the target's vertex q and normal n_q at the associated pixel, the target
    level's intrinsics K = (fx, fy, cx, cy), the pose (R, t), and the levels' first rows and the target's
    size (a term's own images are levels of the same layout: source images at s0 + v, target at t0 + …)."""

    v: object
    u: object
    pt: object
    q: object
    nq: object
    K: object
    R: object
    t: object
    s0: object
    t0: object
    Ht: object
    Wt: object


class TermPass(NamedTuple):
    """A tracking term as one pass of the kernels sees it (``ti_fusion.tracking.terms``): ``row(real)`` makes its
    per-pixel ``ti.func`` (c: Correspondence, mode, src, tgt, settings) → (ok, A, r, w), A the 1×6 Jacobian row
    (rotation first), r the residual, w its weight, ok whether the pixel has a row; ``mode`` a compile-time int
    handed to it; ``source``, ``target`` its own images (tuples of ``Level`` views or fields of the source's and
    the target's layout); ``weight`` λ, its system's factor in the sum solved (the first term's is 1);
    ``settings`` up to TERM_SETTINGS numbers its function reads (e.g. a robust scale)."""

    row: object
    mode: int = 0
    source: tuple = ()
    target: tuple = ()
    weight: float = 1.0
    settings: tuple = ()


# cpu, small sources (run on the calling thread): at least this many pixels per chunk, so that the 30
# partial sums of a chunk cost less than its pixels. (A parallel loop keeps its many chunks: Taichi's CPU
# backend hands out a range-for in tasks of 512 iterations, so fewer chunks would run on one thread.)
MIN_CHUNK_PIXELS = 256


# float32 second pass: the partials are added in this many groups per sum in parallel (a group's total
# in rows [n_chunks, n_chunks + GROUPS) of the partials field), then the groups by one thread per sum.
GROUPS = 128


def default_chunks() -> int:
    """Parallel runs per reduction. Taichi's CPU backend gives each task at least 512 loop iterations,
    so 512 runs per thread are needed to use every thread; GPUs want many more, shorter runs."""
    if on_cpu():
        return 512 * max(2, os.cpu_count() or 2)
    return 16384


_KERNELS: dict = {}


def _blocks(n: int) -> list:
    """range(n) in ranges of at most 30, for nested ``ti.static`` loops: a pass with several terms unrolls its
    register sums on purpose (59 with two, as the depth-only pass its 30), and Taichi warns at every compile
    about a static range of more than 32."""
    return [range(b, min(b + 30, n)) for b in range(0, n, 30)]


# Layout of the ``params`` array every kernel takes (2-D, float64 on cpu, float32 elsewhere): the pose, the
# target intrinsics and the thresholds travel as one small array (cheaper to pass than matrix arguments).
# Row STATE holds the pose (and, for ``reduce`` and ``status_map``, the settings too);
# ``iterate`` reads a level's settings from row SETTINGS + level and keeps its records from row RECORDS on,
# so one array written once per ``align`` and read once after it holds everything that crosses.
P_R, P_T, P_K, P_DIST2, P_COS = 0, 9, 12, 16, 17
# ``iterate`` only: the system's checks (settings row), where its record goes and what it tells the caller
# (state row)
P_MIN_INLIERS, P_STOP, P_LEVEL, P_ITERATION, P_RECORDS, P_DONE = 19, 20, 21, 22, 23, 24
# ``iterate`` only: the level's images (source first row, height, width; the target's) and its chunk count
P_S0, P_HS, P_WS, P_T0, P_HT, P_WT, P_CHUNKS = 25, 26, 27, 28, 29, 30, 31
# each term's columns from P_TERMS: its weight λ, then its settings (``TermPass``)
P_TERMS, TERM_SETTINGS = 32, 3
N_PARAMS = P_TERMS + (1 + TERM_SETTINGS) * MAX_TERMS
STATE, SETTINGS, MAX_LEVELS = 0, 1, 15
RECORDS = SETTINGS + MAX_LEVELS

# One ``iterate`` record: the 30 sums, the pose before the update (R row-major, t), level, iteration,
# ‖δξ‖ and the outcome
R_SUMS, R_POSE, R_LEVEL, R_ITERATION, R_UPDATE, R_OUTCOME, RECORD_LEN = 0, 30, 42, 43, 44, 45, 46
R_TERMS = RECORD_LEN  # the sums of the terms after the first (the pass's sums from N_SUMS on) follow
UPDATED, TOO_FEW_INLIERS, NOT_POSITIVE_DEFINITE = 0, 1, 2
STOPPED, FAILED = 1, 2  # ``params[P_DONE]``: the update fell below P_STOP; the system was not solved
PARAMS_WIDTH = max(N_PARAMS, R_TERMS + n_sums(MAX_TERMS) - N_SUMS)


def term_column(k: int) -> int:
    """The params column of the k-th term's weight (its settings follow)."""
    return P_TERMS + (1 + TERM_SETTINGS) * k


def record_sums(records: np.ndarray, n_terms: int) -> np.ndarray:
    """The sums of ``iterate`` records (rows of the R_* layout) of passes with ``n_terms`` terms."""
    records = np.asarray(records)
    return np.concatenate([records[:, R_SUMS:R_SUMS + N_SUMS], records[:, R_TERMS:R_TERMS + n_sums(n_terms) - N_SUMS]],
                          axis=1)


def _build_kernels(real, state_in_field: bool, term_rows: tuple = ()):
    """The kernels for one arithmetic type (ti.f64 on cpu, ti.f32 on GPU backends); ``iterate``'s and
    ``start``'s state array a field (``state_in_field``: off the CPU) or the host's NumPy array; ``term_rows``
    the ``TermPass.row`` of each term of the passes, in order: their per-pixel functions are unrolled into the
    one pass (``ti.static`` over the terms), so each set of terms is its own instance of ``reduce`` and
    ``iterate``."""
    rows = tuple(make(real) for make in term_rows)
    n_terms = len(rows)
    n_all = n_sums(max(n_terms, 1))  # the pass's sums
    vec3 = ti.types.vector(3, real)
    params_t = ti.types.ndarray(dtype=real, ndim=2)
    out_t = ti.types.ndarray(dtype=real, ndim=1)
    # a field costs a launch less than an ndarray argument does (docs/PERFORMANCE.md, "A fourth H200 lease"),
    # and off the CPU ``iterate`` is launched for every iteration of the schedule
    state_t = ti.template() if state_in_field else params_t

    @ti.func
    def _pose(params: ti.template(), row):
        """(R, t) of the pose in the state row, K of settings row ``row`` (module docstring: params)."""
        R = ti.Matrix([[params[STATE, P_R + 3 * i + j] for j in ti.static(range(3))] for i in ti.static(range(3))],
                      dt=real)
        t = ti.Vector([params[STATE, P_T + i] for i in ti.static(range(3))], dt=real)
        K = ti.Vector([params[row, P_K + i] for i in ti.static(range(4))], dt=real)
        return R, t, K

    @ti.func
    def _target_pixel(src_v: ti.template(), src_n: ti.template(), s0, Ht, Wt, v, u, params: ti.template(), row,
                      tbase, tstride):
        """The first three tests of the association, without branches: the index tbase + vi·tstride + ui of
        the target pixel (vi, ui) that source pixel (v, u) projects to, in the target's field (``_target_base``);
        else, the first test it fails: SOURCE_INVALID (no vertex or normal), BEHIND_TARGET (z′ ≤ 0), NO_TARGET
        (outside the target image)."""
        return _target_pixel_at(src_v, src_n, (s0 + v) * src_v.shape[1] + u, Ht, Wt, params, row, tbase, tstride)

    @ti.func
    def _target_pixel_at(src_v: ti.template(), src_n: ti.template(), sf, Ht, Wt, params: ti.template(), row,
                         tbase, tstride):
        """``_target_pixel`` of the source pixel at index ``sf`` of the source's field (its row times the field's
        width, a compile-time constant, plus its column), which the first pass keeps running: LLVM then reads the
        pixel at sf × its size, without the row's multiplication (docs/PERFORMANCE.md, 2026-11-29)."""
        R, t, K = _pose(params, row)  # per pixel, as the surfel projections (hoisted, it ran slower: docs/KERNELS.md)
        p = ti.cast(src_v[sf // ti.static(src_v.shape[1]), sf % ti.static(src_v.shape[1])], real)
        n = ti.cast(src_n[sf // ti.static(src_v.shape[1]), sf % ti.static(src_v.shape[1])], real)
        pt = R @ p + t
        inv_z = 1.0 / pt.z  # inf or negative where z′ ≤ 0: masked below
        # ⌊x⌋ in [0, W) exactly when x in [0, W), and there truncation is the floor: one conversion,
        # where ti.floor was found to compile to a library call (docs/KERNELS.md)
        uf = K[0] * pt.x * inv_z + K[2] + 0.5
        vf = K[1] * pt.y * inv_z + K[3] + 0.5
        front = pt.z > 0
        inside = front & (0 <= uf) & (uf < Wt) & (0 <= vf) & (vf < Ht)  # NaN compares false
        ui = ti.cast(ti.select(inside, uf, 0.0), ti.i32)
        vi = ti.cast(ti.select(inside, vf, 0.0), ti.i32)
        valid = (p.z > 0) & (n.dot(n) > 0)
        tp = tbase + vi * tstride + ui
        return ti.select(valid, ti.select(inside, tp, ti.select(front, NO_TARGET, BEHIND_TARGET)), SOURCE_INVALID)

    @ti.func
    def _target_base(tgt_v: ti.template(), t0):
        """(tbase, tstride) of ``_target_pixel`` for a target level at row t0 of its field: the pixel's index in
        the whole field, so that ``_correspondence`` finds its row and column by a division by the field's
        width, a compile-time constant, where one by the level's width took an integer division per pixel
        (docs/PERFORMANCE.md: ICP's iteration, 2026-11-29)."""
        tstride = tgt_v.shape[1]  # (``x = ti.static(...)`` would bind a name, not make a variable)
        return t0 * tstride, tstride

    @ti.func
    def _chunk_range(H, W, c, n_chunks):
        """Pixels [begin, end) of chunk c of ``n_chunks`` contiguous runs of the H × W source's pixels."""
        n_pix = H * W
        chunk = (n_pix + n_chunks - 1) // n_chunks
        begin = ti.min(c * chunk, n_pix)
        return begin, ti.min(begin + chunk, n_pix)

    @ti.func
    def _project_chunk(src_v: ti.template(), src_n: ti.template(), s0, W, Ht, Wt, begin, end,
                       params: ti.template(), row, target: ti.template(), tbase, tstride):
        """First pass over a chunk: ``target[k]`` = ``_target_pixel`` of each of its pixels k.

        Every kernel that tests correspondences makes two passes over a chunk: this one projects (no
        branches, no reads of the target), the second reads the target pixel and tests
        (``_correspondence``), while the chunk's ``target`` entries are still in cache: fused into one
        pass, the projection and the target read that depends on it ran slower (docs/KERNELS.md).
        ``reduce`` and ``iterate`` share both passes, so they find the same correspondences."""
        v = begin // W
        u = begin - v * W
        fw = src_v.shape[1]
        sf = (s0 + v) * fw + u  # the pixel's index in the source's field (``_target_pixel_at``)
        for k in range(begin, end):
            target[k] = _target_pixel_at(src_v, src_n, sf, Ht, Wt, params, row, tbase, tstride)
            u += 1
            sf += 1
            if u == W:
                u = 0
                sf += fw - W

    @ti.func
    def _correspondence(src_v: ti.template(), src_n: ti.template(), tgt_v: ti.template(), tgt_n: ti.template(),
                        s0, tp, v, u, R, t, dist2_thr, cos_thr):
        """Second pass, for source pixel (v, u) with target pixel ``tp`` ≥ 0 (``_target_pixel``, its index in the
        target's field: ``_target_base``): (status,
        p′, q, n_q), status the first of the remaining tests it fails (STATUS_TARGET_INVALID,
        STATUS_TOO_FAR, STATUS_NORMAL_ANGLE) or STATUS_OK."""
        status = STATUS_TARGET_INVALID
        pt = vec3(0.0)
        q = ti.cast(tgt_v[tp // ti.static(tgt_v.shape[1]), tp % ti.static(tgt_v.shape[1])], real)
        nq = ti.cast(tgt_n[tp // ti.static(tgt_v.shape[1]), tp % ti.static(tgt_v.shape[1])], real)
        if q.z > 0 and nq.dot(nq) > 0:
            status = STATUS_TOO_FAR
            pt = R @ ti.cast(src_v[s0 + v, u], real) + t
            d = pt - q
            if d.dot(d) < dist2_thr:
                status = STATUS_NORMAL_ANGLE
                if (R @ ti.cast(src_n[s0 + v, u], real)).dot(nq) > cos_thr:
                    status = STATUS_OK
        return status, pt, q, nq

    @ti.func
    def _chunk_sums(src_v: ti.template(), src_n: ti.template(), tgt_v: ti.template(), tgt_n: ti.template(),
                    s0, Hs, W, t0, Ht, Wt, c, n_chunks, params: ti.template(), row, target: ti.template(),
                    terms: ti.template()):
        """The sums of chunk c of ``n_chunks``, in registers (two passes: ``_project_chunk``): at each
        correspondence, each term's row (``rows[j]``, with its mode and images ``terms[j]``) into its 29 sums,
        and the count of valid source pixels."""
        begin, end = _chunk_range(Hs, W, c, n_chunks)
        tbase, tstride = _target_base(tgt_v, t0)
        _project_chunk(src_v, src_n, s0, W, Ht, Wt, begin, end, params, row, target, tbase, tstride)
        R, t, K = _pose(params, row)
        dist2_thr, cos_thr = params[row, P_DIST2], params[row, P_COS]
        settings = [ti.Vector([params[row, ti.static(term_column(j) + 1 + i)] for i in ti.static(range(TERM_SETTINGS))],
                              dt=real) for j in ti.static(range(n_terms))]
        acc = ti.Vector([0.0] * ti.static(n_all), dt=real)
        v = begin // W
        u = begin - v * W
        for k in range(begin, end):
            tp = target[k]
            if tp != SOURCE_INVALID:
                acc[SUM_SOURCE] += 1.0
            if tp >= 0:
                status, pt, q, nq = _correspondence(src_v, src_n, tgt_v, tgt_n, s0, tp, v, u, R, t, dist2_thr,
                                                    cos_thr)
                if status == STATUS_OK:
                    for j in ti.static(range(n_terms)):
                        ok, A, r, w = rows[j](ti.static(Correspondence(v, u, pt, q, nq, K, R, t, s0, t0, Ht, Wt)),
                                              terms[j][0], terms[j][1], terms[j][2], settings[j])
                        if ok:
                            o = ti.static(term_offset(j))
                            wA = w * A
                            for e in ti.static(range(21)):
                                acc[o + e] += wA[UPPER[e][0]] * A[UPPER[e][1]]
                            for e in ti.static(range(6)):
                                acc[o + SUM_ATB + e] += wA[e] * r
                            acc[o + TERM_R2] += r * r
                            acc[o + TERM_COUNT] += 1.0
            u += 1
            if u == W:
                u = 0
                v += 1
        return acc

    @ti.func
    def _partial_sums(src_v: ti.template(), src_n: ti.template(), tgt_v: ti.template(), tgt_n: ti.template(),
                      s0, Hs, Ws, t0, Ht, Wt, partials: ti.template(), n_chunks, params: ti.template(), row,
                      serial: ti.template(), target: ti.template(), terms: ti.template()):
        """``partials[c, :]`` = the sums of chunk c, for every chunk. Call it at a kernel's top level: its
        loop is then the kernel's parallel loop over chunks (float64: on the calling thread with ``serial``).
        In float32 (off the CPU) the loop's bound is the partials' chunk rows, a compile-time constant, and
        chunks past ``n_chunks`` do nothing: a loop with a bound known only on the device is launched as a
        whole device's grid (lavapipe runs that on the CPU, even for a launch after a stop: docs/PERFORMANCE.md)."""
        if ti.static(real == ti.f32):
            for c in range(ti.static(partials.shape[0] - GROUPS)):
                if c < n_chunks:
                    _chunk_into(src_v, src_n, tgt_v, tgt_n, s0, Hs, Ws, t0, Ht, Wt, partials, c, n_chunks, params,
                                row, target, terms)
        else:
            if ti.static(serial):
                ti.loop_config(serialize=True)
            for c in range(n_chunks):  # parallel over chunks, serial (in registers) inside one
                _chunk_into(src_v, src_n, tgt_v, tgt_n, s0, Hs, Ws, t0, Ht, Wt, partials, c, n_chunks, params,
                            row, target, terms)

    @ti.func
    def _chunk_into(src_v: ti.template(), src_n: ti.template(), tgt_v: ti.template(), tgt_n: ti.template(),
                    s0, Hs, Ws, t0, Ht, Wt, partials: ti.template(), c, n_chunks, params: ti.template(), row,
                    target: ti.template(), terms: ti.template()):
        """The sums of chunk c (in registers) into ``partials[c, :]``."""
        acc = _chunk_sums(src_v, src_n, tgt_v, tgt_n, s0, Hs, Ws, t0, Ht, Wt, c, n_chunks, params, row, target,
                          terms)
        for block in ti.static(_blocks(n_all)):
            for e in ti.static(block):
                partials[c, e] = acc[e]

    @ti.func
    def _total(partials: ti.template(), n_chunks, n_sums: ti.template()):
        """The partials of ``n_chunks`` chunks added, serially: ``n_sums`` independent running sums in
        registers."""
        total = ti.Vector([0.0] * n_sums, dt=real)
        for c in range(n_chunks):
            for block in ti.static(_blocks(n_sums)):
                for e in ti.static(block):
                    total[e] += partials[c, e]
        return total

    @ti.func
    def _kahan_range(partials: ti.template(), c0, c1, k):
        """Sum ``k`` of the partials of chunks [c0, c1), Kahan-compensated (float32 stays near float64)."""
        s = ti.cast(0.0, real)
        comp = ti.cast(0.0, real)
        for c in range(c0, c1):
            y = partials[c, k] - comp
            s_new = s + y
            comp = (s_new - s) - y
            s = s_new
        return s

    @ti.func
    def _kahan_groups(partials: ti.template(), n_chunks, n_sums: ti.template()):
        """The float32 second pass's first loop (call it at a kernel's top level: its loop is then one of the
        kernel's parallel loops): for each of ``n_sums`` sums, GROUPS threads add a contiguous run of the
        ``n_chunks`` chunks' partials each, into the group rows after the chunks' (``_group_total`` adds
        those). Static bounds, so the launch is one small grid (with none, a dynamic loop is a whole
        device's; lavapipe runs that on the CPU); no chunks leave zeros."""
        g0 = ti.static(partials.shape[0] - GROUPS)
        per = (n_chunks + GROUPS - 1) // GROUPS
        for g, k in ti.ndrange(GROUPS, n_sums):
            partials[g0 + g, k] = _kahan_range(partials, ti.min(g * per, n_chunks), ti.min(g * per + per, n_chunks),
                                               k)

    @ti.func
    def _group_total(partials: ti.template(), k):
        """Sum ``k`` of the GROUPS group totals ``_kahan_groups`` wrote."""
        g0 = ti.static(partials.shape[0] - GROUPS)
        return _kahan_range(partials, g0, g0 + GROUPS, k)

    @ti.kernel
    def reduce(src_v: ti.template(), src_n: ti.template(), tgt_v: ti.template(), tgt_n: ti.template(),
               s0: ti.i32, Hs: ti.i32, Ws: ti.i32, t0: ti.i32, Ht: ti.i32, Wt: ti.i32,
               partials: ti.template(), n_chunks: ti.i32, params: params_t, out: out_t, serial: ti.template(),
               target: ti.template(), terms: ti.template()):
        """The pass's sums (``n_sums``) into ``out`` (and the per-chunk partials into ``partials[:n_chunks]``);
        ``serial``: the chunks run on the calling thread (small levels on the CPU, see ``PointToPlane``);
        ``target``: scratch of one int per source pixel; ``terms``: each term's (mode, source images, target
        images)."""
        _partial_sums(src_v, src_n, tgt_v, tgt_n, s0, Hs, Ws, t0, Ht, Wt, partials, n_chunks, params, STATE, serial,
                      target, terms)
        n_sums = ti.static(n_all)
        # Runs after the loop above has finished: add the partials.
        if ti.static(real == ti.f64):  # cpu: one serial pass, independent running sums in registers
            # on the calling thread: handing even a one-iteration loop to the thread pool costs more
            ti.loop_config(serialize=True)
            for _ in range(1):
                total = _total(partials, n_chunks, n_sums)
                for block in ti.static(_blocks(n_sums)):
                    for k in ti.static(block):
                        out[k] = total[k]
        else:  # float32 (GPU backends): groups of chunks in parallel, then their totals; Kahan-compensated
            _kahan_groups(partials, n_chunks, n_sums)
            for k in range(n_sums):
                out[k] = _group_total(partials, k)

    @ti.func
    def _solve_cholesky(system):
        """(δξ, ok) with (Σ w AᵀA) δξ = −Σ w Aᵀb from the 30 sums, by Cholesky; ok is False when a pivot is
        not positive (or not a number): the system is not positive definite. In float32 the system is first
        scaled to a unit diagonal (Jacobi), which takes the ratio of the rotation and translation columns'
        scales out of the condition number the float32 factorisation sees."""
        total = system
        d = ti.Vector([1.0] * 6, dt=real)
        if ti.static(real == ti.f32):
            for i in ti.static(range(6)):
                a = system[ti.static(UPPER.index((i, i)))]
                if a > 0:
                    d[i] = 1.0 / ti.sqrt(a)
            for e in ti.static(range(21)):
                total[e] = system[e] * d[UPPER[e][0]] * d[UPPER[e][1]]
            for i in ti.static(range(6)):
                total[SUM_ATB + i] = system[SUM_ATB + i] * d[i]
        L = ti.Matrix.zero(real, 6, 6)
        ok = True
        for i in ti.static(range(6)):
            for j in ti.static(range(i + 1)):
                a = total[ti.static(UPPER.index((j, i)))]  # AᵀA[j, i], upper triangle
                for k in ti.static(range(j)):
                    a -= L[i, k] * L[j, k]
                if ti.static(i == j):
                    if not a > 0:  # also NaN
                        ok = False
                    L[i, i] = ti.sqrt(ti.max(a, ti.static(1e-300 if real == ti.f64 else 1e-30)))
                else:
                    L[i, j] = a / L[j, j]
        y = ti.Vector.zero(real, 6)
        for i in ti.static(range(6)):
            a = -total[SUM_ATB + i]
            for k in ti.static(range(i)):
                a -= L[i, k] * y[k]
            y[i] = a / L[i, i]
        x = ti.Vector.zero(real, 6)
        for i in ti.static(range(5, -1, -1)):
            a = y[i]
            for k in ti.static(range(i + 1, 6)):
                a -= L[k, i] * x[k]
            x[i] = a / L[i, i]
        return x * d, ok

    @ti.func
    def _se3_exp(xi):
        """(R, t) of exp(ξ), ξ = (ω, v) rotation first: ``ti_fusion.geometry.se3_exp`` term by term."""
        w = ti.Vector([xi[0], xi[1], xi[2]], dt=real)
        theta = w.norm()
        W = ti.Matrix([[0.0, -w.z, w.y], [w.z, 0.0, -w.x], [-w.y, w.x, 0.0]], dt=real)
        WW = W @ W
        a, b, c = ti.cast(1.0, real), ti.cast(0.5, real), ti.cast(1.0 / 6.0, real)
        if ti.static(real == ti.f32):  # float32: the series, where 1 − cos θ and θ − sin θ cancel to noise
            t2 = theta * theta
            a, b, c = 1.0 - t2 / 6.0, 0.5 - t2 / 24.0, 1.0 / 6.0 - t2 / 120.0
        if theta >= ti.static(1e-8 if real == ti.f64 else 1e-2):
            a = ti.sin(theta) / theta
            b = (1.0 - ti.cos(theta)) / (theta * theta)
            c = (theta - ti.sin(theta)) / (theta * theta * theta)
        eye = ti.Matrix.identity(real, 3)
        R = eye + a * W + b * WW
        J = eye + b * W + c * WW
        return R, J @ ti.Vector([xi[3], xi[4], xi[5]], dt=real)

    @ti.func
    def _runs(params: ti.template(), it):
        """Whether an ``iterate`` launch does its iteration: not after a failure, and within a level not
        after the update fell below the stop threshold (a level's first iteration starts it again)."""
        done = params[STATE, P_DONE]
        return (done != FAILED) & ((done != STOPPED) | (it == 0))

    @ti.func
    def _iteration_sums(src_v: ti.template(), src_n: ti.template(), tgt_v: ti.template(), tgt_n: ti.template(),
                        partials: ti.template(), params: ti.template(), serial: ti.template(), target: ti.template(),
                        terms: ti.template(), row, it):
        """``iterate``'s sums at the level of settings row ``row``: the partials of its chunks (none when the
        launch does nothing), and off the CPU their Kahan-compensated totals into the record."""
        n_sums = ti.static(n_all)
        runs = _runs(params, it)
        n_chunks = ti.select(runs, ti.cast(params[row, P_CHUNKS], ti.i32), 0)
        s0 = ti.cast(params[row, P_S0], ti.i32)
        Hs = ti.cast(params[row, P_HS], ti.i32)
        Ws = ti.cast(params[row, P_WS], ti.i32)
        t0 = ti.cast(params[row, P_T0], ti.i32)
        Ht = ti.cast(params[row, P_HT], ti.i32)
        Wt = ti.cast(params[row, P_WT], ti.i32)
        _partial_sums(src_v, src_n, tgt_v, tgt_n, s0, Hs, Ws, t0, Ht, Wt, partials, n_chunks, params, row, serial,
                      target, terms)
        if ti.static(real == ti.f32):  # groups of chunks in parallel, then one thread per sum, into the record
            _kahan_groups(partials, n_chunks, n_sums)  # n_chunks is 0 when the launch does nothing
            for e in range(n_sums):  # a static bound too: the test inside
                if runs:
                    k = RECORDS + ti.cast(params[STATE, P_RECORDS], ti.i32)
                    params[k, ti.select(e < N_SUMS, R_SUMS + e, R_TERMS + e - N_SUMS)] = _group_total(partials, e)

    @ti.func
    def _iteration_solve(partials: ti.template(), params: ti.template(), row, it):
        """``iterate``'s serial part, on the calling thread: the record, the checks, the Cholesky solve and
        the update of the pose in the state row."""
        n_sums = ti.static(n_all)
        runs = _runs(params, it)
        n_chunks = ti.select(runs, ti.cast(params[row, P_CHUNKS], ti.i32), 0)
        ti.loop_config(serialize=True)  # on the calling thread, as reduce's sum
        for _ in range(ti.select(runs, 1, 0)):
            k = RECORDS + ti.cast(params[STATE, P_RECORDS], ti.i32)
            total = ti.Vector([0.0] * n_sums, dt=real)
            if ti.static(real == ti.f64):
                total = _total(partials, n_chunks, n_sums)
                for e in ti.static(range(N_SUMS)):
                    params[k, R_SUMS + e] = total[e]
                for e in ti.static(range(n_sums - N_SUMS)):
                    params[k, R_TERMS + e] = total[N_SUMS + e]
            else:
                for e in ti.static(range(N_SUMS)):
                    total[e] = params[k, R_SUMS + e]
                for e in ti.static(range(n_sums - N_SUMS)):
                    total[N_SUMS + e] = params[k, R_TERMS + e]
            system = ti.Vector([total[e] for e in ti.static(range(N_SUMS))], dt=real)
            for j in ti.static(range(1, n_terms)):  # the other terms, each × its λ
                lam = params[row, ti.static(term_column(j))]
                for e in ti.static(range(27)):
                    system[e] += lam * total[ti.static(term_offset(j) + e)]
            for e in ti.static(range(12)):
                params[k, R_POSE + e] = params[STATE, P_R + e]
            params[k, R_LEVEL] = params[row, P_LEVEL]
            params[k, R_ITERATION] = it
            outcome = TOO_FEW_INLIERS
            update = ti.cast(0.0, real)
            if total[SUM_INLIERS] >= params[row, P_MIN_INLIERS]:
                xi, ok = _solve_cholesky(system)
                update = xi.norm()
                outcome = NOT_POSITIVE_DEFINITE
                if ok and update < 1e30:  # (a NaN fails the comparison)
                    outcome = UPDATED
                    dR, dt = _se3_exp(xi)
                    R, t, K = _pose(params, row)
                    R_new = dR @ R
                    t_new = dR @ t + dt
                    for i in ti.static(range(3)):
                        for j in ti.static(range(3)):
                            params[STATE, P_R + 3 * i + j] = R_new[i, j]
                        params[STATE, P_T + i] = t_new[i]
            params[k, R_UPDATE] = update
            params[k, R_OUTCOME] = outcome
            params[STATE, P_RECORDS] = k + 1 - RECORDS
            params[STATE, P_DONE] = ti.select(outcome != UPDATED, FAILED,
                                              ti.select(update < params[row, P_STOP], STOPPED, 0.0))

    @ti.kernel
    def iterate(src_v: ti.template(), src_n: ti.template(), tgt_v: ti.template(), tgt_n: ti.template(),
                partials: ti.template(), params: state_t, serial: ti.template(), target: ti.template(),
                terms: ti.template(), row: ti.i32, it: ti.i32):
        """One whole ICP iteration in one launch, at the level of settings row ``row`` (its images' first
        rows and sizes and its chunk count are in that row, written once per ``align``): the sums as
        ``reduce``, then on one thread the checks, the Cholesky solve and the update T ← exp(δξ) T of the
        pose in the state row (written back in place). Appends a record (R_* layout) at row RECORDS +
        ``params[STATE, P_RECORDS]`` and sets ``params[STATE, P_DONE]`` to FAILED when the system was not
        solved, STOPPED when ‖δξ‖ fell below the level's P_STOP. After FAILED, and after STOPPED until the
        next level's first iteration (``it`` = 0), a launch does nothing: its loops run zero times, so the
        caller may launch every iteration of the schedule without reading anything back. The caller
        replays the records (``ti_fusion.tracking.icp``), with the condition-number check of
        ``ti_fusion.tracking.solve`` too, which is why it is not repeated here. The system solved is the first
        term's plus λ × each other term's (module docstring), and the record holds the other terms' sums from
        R_TERMS on. Float64 backends add the partials serially, float32 ones in groups and
        then the group totals (Kahan-compensated, as ``reduce``) into the record, which the solve then reads."""
        _iteration_sums(src_v, src_n, tgt_v, tgt_n, partials, params, serial, target, terms, row, it)
        _iteration_solve(partials, params, row, it)

    @ti.kernel
    def iterate_sums(src_v: ti.template(), src_n: ti.template(), tgt_v: ti.template(), tgt_n: ti.template(),
                     partials: ti.template(), params: state_t, serial: ti.template(), target: ti.template(),
                     terms: ti.template(), row: ti.i32, it: ti.i32):
        """On the CPU, ``iterate`` as two launches, this one's sums then ``iterate_solve``: the halves compile
        in about two thirds of the whole's time (docs/PERFORMANCE.md), for one launch more per iteration."""
        _iteration_sums(src_v, src_n, tgt_v, tgt_n, partials, params, serial, target, terms, row, it)

    @ti.kernel
    def iterate_solve(partials: ti.template(), params: state_t, row: ti.i32, it: ti.i32):
        """``iterate``'s record, solve and update, after ``iterate_sums``."""
        _iteration_solve(partials, params, row, it)

    @ti.kernel
    def start(params: state_t, pose: ti.types.vector(12, real)):
        """Off the CPU, the start of an ``align``: the pose into the state row, no records, not done. A
        launch with the pose as an argument, where copying the state array from NumPy would wait for the
        device (Taichi copies a NumPy argument back after the kernel)."""
        ti.loop_config(serialize=True)
        for _ in range(1):
            for e in ti.static(range(12)):
                params[STATE, P_R + e] = pose[e]
            params[STATE, P_RECORDS] = 0
            params[STATE, P_DONE] = 0

    @ti.kernel
    def status_map(src_v: ti.template(), src_n: ti.template(), tgt_v: ti.template(), tgt_n: ti.template(),
                   s0: ti.i32, Hs: ti.i32, Ws: ti.i32, t0: ti.i32, Ht: ti.i32, Wt: ti.i32,
                   status: ti.template(), params: params_t):
        for v, u in ti.ndrange(Hs, Ws):
            tbase, tstride = _target_base(tgt_v, t0)
            tp = _target_pixel(src_v, src_n, s0, Ht, Wt, v, u, params, STATE, tbase, tstride)
            s = ti.select(tp == SOURCE_INVALID, STATUS_SOURCE_INVALID,
                          ti.select(tp == BEHIND_TARGET, STATUS_BEHIND, STATUS_OUT_OF_IMAGE))
            if tp >= 0:
                R, t, K = _pose(params, STATE)
                s, pt, q, nq = _correspondence(src_v, src_n, tgt_v, tgt_n, s0, tp, v, u, R, t,
                                               params[STATE, P_DIST2], params[STATE, P_COS])
            status[v, u] = s

    return {"reduce": reduce, "iterate": iterate, "iterate_sums": iterate_sums, "iterate_solve": iterate_solve,
            "start": start, "status_map": status_map}


def kernels_for(real, state_in_field: bool = False, term_rows: tuple = ()):
    """The kernels of one arithmetic type and state location, with ``reduce`` and ``iterate`` for the terms
    whose ``TermPass.row`` are ``term_rows`` (made once per set of terms)."""
    key = (real, state_in_field, tuple(term_rows))
    if key not in _KERNELS:
        _KERNELS[key] = _build_kernels(real, state_in_field, tuple(term_rows))
    return _KERNELS[key]


@data_oriented
class PointToPlane:
    """Association + linearisation + reduction for one backend, with the fields the passes write.

    ``max_pixels``: the largest source level (H·W) it will see. Poses are 4×4 NumPy arrays mapping
    source-camera points into the target camera; intrinsics are (fx, fy, cx, cy) of the TARGET level.
    Images (``src_v`` … ``tgt_n``) are ``Level`` views or plain 2-D fields (module docstring).
    """

    def __init__(self, max_pixels: int, has_f64: bool, n_chunks: int | None = None,
                 min_chunk_pixels: int | None = None):
        self.real = ti.f64 if has_f64 else ti.f32
        self.np_real = np.float64 if has_f64 else np.float32
        self.max_pixels = int(max_pixels)
        self.n_chunks = int(n_chunks or default_chunks())
        # GPUs want one short chunk per thread; on the CPU a chunk run serially should outweigh its bookkeeping
        self.min_chunk_pixels = int(min_chunk_pixels or (MIN_CHUNK_PIXELS if on_cpu() else 1))
        self.serial_below = SERIAL_BELOW if on_cpu() else 0  # smaller sources run on the calling thread
        # one choice for every level (each choice is an instance of the kernels): small maximum, serial
        self.serial = self.max_pixels < self.serial_below
        self.on_host = on_cpu()  # kernels read and write NumPy arrays in place: nothing to copy
        self.k = kernels_for(self.real, state_in_field=not self.on_host)  # ``start``, ``status_map``
        # per chunk, then (float32) the GROUPS group totals of the second pass; one field per number of sums
        self.partials = ti.field(self.real, shape=(self.n_chunks + GROUPS, N_SUMS))
        self._partials = {N_SUMS: self.partials}
        self.target = ti.field(ti.i32, shape=self.max_pixels)  # per-pixel scratch (``_project_chunk``)
        self.state = None  # ``iterate``'s params: state, settings, records (``begin_iterations``)
        self.state_device = None  # off the CPU, its copy on the device (a Taichi field)
        self._device_newer = False  # the device copy has records the host copy lacks
        self._settings_on_device = None  # the settings rows last copied to the device
        self.params = np.zeros((1, N_PARAMS), dtype=self.np_real)
        self._out = {}  # number of sums → the array ``reduce`` writes (no copy on cpu)
        self.status_field = {}

    def _set_params(self, T: np.ndarray | None, K, dist_threshold: float, normal_threshold_deg: float,
                    terms: tuple = ()) -> np.ndarray:
        """Fill ``params`` for a pass (T None: leave the pose as it is)."""
        self._fill(self.params[STATE], T, K, dist_threshold, normal_threshold_deg, terms)
        return self.params

    @staticmethod
    def _fill(p: np.ndarray, T, K, dist_threshold: float, normal_threshold_deg: float, terms) -> None:
        """One row of params: the pose (unless T is None), a pass's settings and each term's weight and settings."""
        if T is not None:
            p[P_R:P_T + 3] = flatten_pose(T)
        p[P_K:P_K + 4] = [float(x) for x in K]
        p[P_DIST2] = float(dist_threshold) ** 2
        p[P_COS] = math.cos(math.radians(normal_threshold_deg))
        for k, term in enumerate(terms):
            if len(term.settings) > TERM_SETTINGS:
                raise ValueError(f"a tracking term has {len(term.settings)} settings; at most {TERM_SETTINGS}")
            c = term_column(k)
            p[c] = float(term.weight)
            p[c + 1:c + 1 + len(term.settings)] = [float(x) for x in term.settings]

    @staticmethod
    def _images(src_v, src_n, tgt_v, tgt_n) -> tuple:
        """The kernels' first ten arguments: the four images' fields, then the source's first row, height
        and width and the target's (``Level`` views or plain fields; module docstring)."""
        s, sn, t, tn = as_level(src_v), as_level(src_n), as_level(tgt_v), as_level(tgt_n)
        if (sn.row0, sn.shape) != (s.row0, s.shape) or (tn.row0, tn.shape) != (t.row0, t.shape):
            raise ValueError("vertex and normal images of one side must be levels of the same layout")
        return (s.field, sn.field, t.field, tn.field, s.row0, *s.shape, t.row0, *t.shape)

    def _terms(self, images: tuple, terms) -> tuple:
        """(kernels, partials, out, per-term arguments) of a pass with ``terms`` (``TermPass``, the first the
        one whose count is the inliers): each term's arguments are its mode and its images' fields, which must
        be levels of the source's and the target's layout."""
        terms = tuple(terms)
        if not 1 <= len(terms) <= MAX_TERMS:
            raise ValueError(f"a pass has 1 to {MAX_TERMS} tracking terms, not {len(terms)}")
        args = []
        for term in terms:
            sides = []
            layouts = ((term.source, (images[4], images[5:7])), (term.target, (images[7], images[8:10])))
            for side, (row0, shape) in layouts:
                levels = [as_level(x) for x in side]
                if any((lv.row0, lv.shape) != (row0, shape) for lv in levels):
                    raise ValueError("a tracking term's images must be levels of the same layout as the vertex images")
                sides.append(tuple(lv.field for lv in levels))
            args.append((int(term.mode), *sides))
        n = n_sums(len(terms))
        if n not in self._partials:
            self._partials[n] = ti.field(self.real, shape=(self.n_chunks + GROUPS, n))
        if n not in self._out:
            self._out[n] = np.zeros(n, dtype=self.np_real)
        k = kernels_for(self.real, not self.on_host, tuple(term.row for term in terms))
        return k, self._partials[n], self._out[n], tuple(args)

    def _chunks(self, images: tuple) -> int:
        """Chunks of a pass over the source of ``images``: small levels (fewer than ``serial_below``
        pixels) in chunks of at least ``min_chunk_pixels``, run by one thread (serially, or as one task of
        the parallel loop), larger ones in ``n_chunks`` shared by the threads."""
        n = images[5] * images[6]
        if n > self.max_pixels:
            raise ValueError(f"source of {n} pixels given to a PointToPlane sized for {self.max_pixels}")
        if n < self.serial_below:
            return max(1, min(self.n_chunks, n // self.min_chunk_pixels))
        return min(self.n_chunks, n)

    def reduce(self, src_v, src_n, tgt_v, tgt_n, T, K, dist_threshold: float, normal_threshold_deg: float,
               terms) -> np.ndarray:
        """The sums (float64 NumPy, ``n_sums(len(terms))``) of one association + linearisation pass at pose
        ``T`` with ``terms`` (``TermPass``, e.g. ``ti_fusion.tracking.terms``' ``kernel_pass``)."""
        images = self._images(src_v, src_n, tgt_v, tgt_n)
        n_chunks = self._chunks(images)
        params = self._set_params(T, K, dist_threshold, normal_threshold_deg, terms)
        k, partials, out, args = self._terms(images, terms)
        k["reduce"](*images, partials, n_chunks, params, out, self.serial, self.target, args)
        return out.astype(np.float64)

    # -- whole iterations in the kernel ----------------------------------------------------------------
    @property
    def solves_in_kernel(self) -> bool:
        """Whether ``iterate`` is available: on every backend (float64 on the CPU, float32 with a Jacobi-
        scaled Cholesky elsewhere)."""
        return True

    @property
    def records(self) -> np.ndarray:
        """The host copy of ``iterate``'s record rows (capacity × PARAMS_WIDTH)."""
        return self.state[RECORDS:]

    def begin_iterations(self, T: np.ndarray, max_records: int) -> None:
        """Start a run of ``iterate`` calls at pose ``T`` with room for ``max_records`` records. Then
        ``begin_level`` for every level, before the first ``iterate``: off the CPU the settings cross to the
        device once, with the first launch."""
        rows = RECORDS + max(64, max_records)
        if self.state is None or self.state.shape[0] < rows:
            if self.state is not None:  # at least double: each new device field is a new instance of ``iterate``
                rows = max(rows, RECORDS + 2 * (self.state.shape[0] - RECORDS))
            self.state = np.zeros((rows, PARAMS_WIDTH), dtype=self.np_real)
            if not self.on_host:
                # The field it replaces stays allocated (a few kB; the doubling bounds how many): freeing it,
                # by a tree of its own destroyed, would make Taichi 1.7 drop every compiled kernel of the program.
                self.state_device = ti.field(self.real, shape=self.state.shape)
                self._settings_on_device = None
        self.state[STATE, P_R:P_T + 3] = flatten_pose(T)
        self.state[STATE, P_RECORDS] = 0
        self.state[STATE, P_DONE] = 0
        self._levels = {}
        self._launched = 0
        self._uploaded = False
        self._device_newer = False

    def begin_level(self, src_v, src_n, tgt_v, tgt_n, K, dist_threshold: float, normal_threshold_deg: float,
                    level: int, min_inliers: int, stop_update: float, terms) -> None:
        """Settings of the ``iterate`` calls at ``level``: its images (source vertex and normal, target
        vertex and normal), thresholds and tracking terms (``TermPass``: their images, weights and settings),
        in its settings row; the pose is the one the previous iteration left."""
        if not 0 <= level < MAX_LEVELS:
            raise ValueError(f"pyramid level {level}: ICP runs on levels 0 to {MAX_LEVELS - 1}")
        if self._uploaded:
            raise ValueError("begin_level after the first iterate of a run: call begin_iterations first")
        p = self.state[SETTINGS + level]
        self._fill(p, None, K, dist_threshold, normal_threshold_deg, terms)
        p[P_LEVEL], p[P_MIN_INLIERS], p[P_STOP] = level, min_inliers, stop_update
        # worked out once per level: a Taichi field's .shape costs microseconds per call
        images = self._images(src_v, src_n, tgt_v, tgt_n)
        n_chunks = self._chunks(images)
        p[P_S0], p[P_HS], p[P_WS], p[P_T0], p[P_HT], p[P_WT] = images[4:10]
        p[P_CHUNKS] = n_chunks
        self._levels[level] = (images[:4],) + self._terms(images, terms)
        self._level = level

    def iterate(self, iteration: int, level: int | None = None) -> int:
        """One ICP iteration in one launch (``iterate`` kernel; on the CPU ``iterate_sums`` and ``iterate_solve``)
        at ``level`` (default: the last one begun).
        On the CPU, where the kernel writes the host's array in place: 0, or STOPPED / FAILED (stop the
        level / the run), so the caller launches no more than needed. Elsewhere nothing is read back: 0,
        and the caller launches the whole schedule, whose iterations after a stop are no-ops on the device."""
        level = self._level if level is None else level
        images, k, partials, _, terms = self._levels[level]
        if self._launched >= self.records.shape[0]:  # the kernel could write past the records
            raise ValueError(f"more than {self.records.shape[0]} iterations since begin_iterations")
        self._launched += 1
        params = self.state
        if not self.on_host:
            if not self._uploaded:
                self._start_on_device()
            params = self.state_device
            self._device_newer = True
        self._uploaded = True
        if self.on_host:  # two kernels that compile faster than one; a launch costs the CPU microseconds
            k["iterate_sums"](*images, partials, params, self.serial, self.target, terms, SETTINGS + level, iteration)
            k["iterate_solve"](partials, params, SETTINGS + level, iteration)
            return int(self.state[STATE, P_DONE])
        k["iterate"](*images, partials, params, self.serial, self.target, terms, SETTINGS + level, iteration)
        return 0

    def _start_on_device(self) -> None:
        """The settings rows to the device where they changed (a copy from NumPy waits for the device, so
        only when an ``align`` brings other thresholds, images or sizes, not every frame), then the pose."""
        settings = self.state[SETTINGS:RECORDS]
        if self._settings_on_device is None or not np.array_equal(settings, self._settings_on_device):
            self.state_device.from_numpy(self.state)
            self._settings_on_device = settings.copy()
        self.k["start"](self.state_device, self.state[STATE, P_R:P_T + 3].copy())

    def _host_state(self) -> np.ndarray:
        """The state array with the device's records and pose: off the CPU, one read for the whole run."""
        if self._device_newer:
            self.state = self.state_device.to_numpy()
            self._device_newer = False
        return self.state

    def iteration_records(self) -> np.ndarray:
        """The records of the iterations since ``begin_iterations`` (float64, one row each, R_* layout;
        ``record_sums`` reads their sums)."""
        state = self._host_state()
        n = int(state[STATE, P_RECORDS])
        return state[RECORDS:RECORDS + n, :PARAMS_WIDTH].astype(np.float64)

    def pose(self) -> np.ndarray:
        """The pose ``iterate`` has reached (4×4 float64)."""
        return unflatten_pose(self._host_state()[STATE, P_R:P_T + 3].astype(np.float64))

    def status(self, src_v, src_n, tgt_v, tgt_n, T, K, dist_threshold: float,
               normal_threshold_deg: float) -> np.ndarray:
        """Per-source-pixel association status codes (int32 H×W; STATUS_* above). For tests and plots."""
        images = self._images(src_v, src_n, tgt_v, tgt_n)
        shape = images[5:7]
        if shape not in self.status_field:
            self.status_field[shape] = ti.field(ti.i32, shape=shape)
        field = self.status_field[shape]
        self.k["status_map"](*images, field, self._set_params(T, K, dist_threshold, normal_threshold_deg))
        return field.to_numpy()
