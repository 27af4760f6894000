"""Compiled per-pixel loops (numba) of the engine's merges: tables, 3x3 matrices, Gaussians, Ward's bitmaps.

The table plan's merge (:func:`table_merge_rows`, run by
:func:`derender.engine.table_kernel.table_kernel_merge`), the matrix plan's
(:func:`stabilized_merge_rows`, run by :func:`derender.engine.matrix.merge_matrix_frames`), the
Gaussian plan's (:func:`gaussian_band`, run by
:func:`derender.engine.gaussian.merge_gaussian_frames`) and the MTB registration's counts
(:func:`mtb_band_counts`, :mod:`derender.engine.motion.ward2003`); their shared inlined steps
are in :mod:`derender.engine.merge_parts`, the variance passes in
:mod:`derender.engine.variance_kernels`.

Where a merge is a short chain of table look-ups per pixel and exposure, one compiled
pass that keeps the pixel's sums in registers beats a chain of whole-array NumPy or
OpenCV passes (each of which reads and writes every plane). The kernels are compiled on
first use and cached on disk (``cache=True``). The merge runs its rows in parallel
(``prange``), every pixel independently, so results do not depend on the thread count;
callers serialise its launches (:data:`derender.engine.matrix.KERNEL_LOCK`), since numba's
fallback thread pool cannot run two parallel kernels at once. The merge divides only by
quantities it has bounded away from 0, so it uses NumPy's error model (no zero-division
check per division; bit-identical results, 2-3 % faster). Importing numba and loading
a cached kernel costs ~0.5-0.8 s here, so the merges do it in a background thread while
they decode (:func:`derender.engine.matrix.warm_up_kernels`,
:func:`derender.engine.table_kernel.warm_up_kernel`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from derender.engine.merge_parts import add_frame_to_tile, add_table_observation, fallback_frame

__all__ = [
    "MERGE_TILE",
    "stabilized_merge_rows",
    "mtb_band_counts",
    "table_merge_rows",
    "gaussian_band",
    "gaussian_moments_band",
    "log_tables_rows",
    "mark_colours",
    "normal_cdf",
    "table_mu",
]


#: Pixels per tile of a row in :func:`stabilized_merge_rows`: every frame is added to the
#: tile's sums in turn (one frame's tables and matrix stay in registers and L1 across the
#: tile; the sums, 8 KB, in L1). Measured on the 24 MP bracket, 2 threads, against one
#: pixel at a time over all frames: 128 px -22 %, 256 -23 %, 512 -28 % (noisy), 2048 and
#: whole rows -12 to -16 %; bit-identical results.
MERGE_TILE = 256


# Positional on purpose: a numba kernel takes plain arrays and scalars (no records, no keyword defaults).
@njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def stabilized_merge_rows(frames, shifts, valid, ref, lin, mats32, mats64, weights, inv_var, inv_k, use_inv_var,
                          colour_w, use_colour_w, j_short, j_long, bright, y0, y1, row0, out, mask):  # pragma: no cover - compiled
    """Rows ``y0:y1`` of the stabilised merge of paper 1 (Algorithm 1 step 4) from 8-bit codes.

    ``frames`` (N, H, W, 3) uint8; image ``j`` is read at ``(y + shifts[j, 0], x + shifts[j, 1])``
    and takes part only inside the frame and where ``valid[j, y, x]`` (``valid`` of shape
    (N, 1, 1) means everywhere). Image ``j`` contributes ``E_j = max(mats32[j] @ lin[j][z], 0)``
    (its estimate projected onto the non-negative orthant, the nearest radiance that can
    exist: a 3x3 matrix with negative off-diagonals, fitted on near-neutral colours, sends a
    saturated colour's weak channel below 0) with
    weight ``w_j = w(z) * inv_k[j] / max(sum_c inv_var[j, z_c, c], 1e-30)`` (the last factor
    only if ``use_inv_var``), times ``colour_w[R << 16 | G << 8 | B]`` of the pixel's colour in
    frame j if ``use_colour_w`` (a per-colour reliability, e.g. the inverse relative variance
    of a de-rendering model), where ``w(z)`` is the smallest channel weight
    ``min_c weights[z_c, c]`` if some image sees all channels of the pixel with positive
    weight, else the weight of the brightest channel ``weights[max_c z_c, 0]``. Both sums are
    kept and the right one chosen at the end. Where the chosen weights sum to 0 the value
    comes from the shortest exposure (``mask`` 1) if its largest code is ``bright``, else from
    the longest (``mask`` 2); where frames are left out (``valid``, ``ref >= 0``: the engine's
    reference frame) the reference's largest code decides instead, and the value comes from the
    shortest frame taking part that is bright there (the tightest lower bound), else from the
    longest one that is not (the tightest upper bound), with ``mats64`` (projected as above); elsewhere ``mask`` is 0. ``out`` is
    (3, rows, W) float32, row ``y`` at ``out[:, y - row0]`` (the whole image: ``row0`` 0; a band
    buffer: its first row). Rows run in parallel; within a row, tiles of :data:`MERGE_TILE`
    pixels take the frames one after another (each pixel's sums still run over the frames in
    order, so the sums are those of a per-pixel loop).
    """
    n = frames.shape[0]
    h, w = frames.shape[1], frames.shape[2]
    whole = valid.shape[1] == 1 and valid.shape[2] == 1
    zero = np.float32(0.0)
    tile = MERGE_TILE
    for y in prange(y0, y1):
        acc = np.empty((8, tile), dtype=np.float32)     # per pixel of the tile: both weight sets' sums
        usable = np.empty(tile, dtype=np.bool_)
        for x0 in range(0, w, tile):
            xe = min(x0 + tile, w)
            acc[:, :] = zero
            usable[:] = False
            for j in range(n):
                yy = y + shifts[j, 0]
                if yy < 0 or yy >= h:
                    continue
                add_frame_to_tile(frames, valid, whole, j, y, yy, shifts[j, 1], x0, xe, w, weights, inv_var,
                                   inv_k[j], use_inv_var, colour_w, use_colour_w, lin, mats32, acc, usable)
            for x in range(x0, xe):
                t = x - x0
                k = 0 if usable[t] else 4
                dm = acc[k, t]
                if dm > zero:
                    out[0, y - row0, x] = acc[k + 1, t] / dm
                    out[1, y - row0, x] = acc[k + 2, t] / dm
                    out[2, y - row0, x] = acc[k + 3, t] / dm
                    mask[y, x] = 0
                    continue
                jj, code = fallback_frame(frames, valid, whole, ref, shifts, j_short, j_long, bright, y, x, h, w)
                mask[y, x] = code
                ys = min(max(y + shifts[jj, 0], 0), h - 1)
                xs = min(max(x + shifts[jj, 1], 0), w - 1)
                e0 = np.float64(lin[jj, frames[jj, ys, xs, 0], 0])
                e1 = np.float64(lin[jj, frames[jj, ys, xs, 1], 1])
                e2 = np.float64(lin[jj, frames[jj, ys, xs, 2], 2])
                for c in range(3):
                    out[c, y - row0, x] = np.float32(max(e0 * mats64[jj, c, 0] + e1 * mats64[jj, c, 1]
                                                  + e2 * mats64[jj, c, 2], 0.0))


@njit(inline="always")
def _popcount64(v):  # pragma: no cover - compiled
    """Set bits of a uint64 (SWAR; LLVM turns the idiom into ``popcnt``)."""
    v = v - ((v >> np.uint64(1)) & np.uint64(0x5555555555555555))
    v = (v & np.uint64(0x3333333333333333)) + ((v >> np.uint64(2)) & np.uint64(0x3333333333333333))
    v = (v + (v >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return (v * np.uint64(0x0101010101010101)) >> np.uint64(56)


@njit(nogil=True, cache=True)
def _pack_row(grey, y, shift, med, lo, hi, tw, ew):  # pragma: no cover - compiled
    """Threshold (``g > med``) and exclusion (``g < lo or g > hi``) bits of row ``y`` read at
    ``x + shift`` (0 outside the row), 64 pixels per word, into ``tw`` / ``ew``."""
    w = grey.shape[1]
    x0, x1 = max(0, -shift), min(w, w - shift)
    for k in range(tw.shape[0]):
        t = np.uint64(0)
        e = np.uint64(0)
        base = k * 64
        for x in range(max(base, x0), min(base + 64, x1)):
            g = np.int64(grey[y, x + shift])
            b = np.uint64(x - base)
            t |= np.uint64(g > med) << b
            e |= np.uint64((g < lo) | (g > hi)) << b
        tw[k] = t
        ew[k] = e


@njit(nogil=True, cache=True)
def _shift_words(src, shift, dst):  # pragma: no cover - compiled
    """Packed row read at ``x + shift``: bit ``x`` of ``dst`` is bit ``x + shift`` of ``src``
    (0 beyond its words; a packed row's bits past the image width are 0)."""
    nw = src.shape[0]
    q = shift // 64                      # floor division: shift = 64 q + r, 0 <= r < 64
    r = np.uint64(shift - 64 * q)
    for k in range(nw):
        i = k + q
        lo = src[i] if 0 <= i < nw else np.uint64(0)
        if r == 0:
            dst[k] = lo
        else:
            hi = src[i + 1] if 0 <= i + 1 < nw else np.uint64(0)
            dst[k] = (lo >> r) | (hi << (np.uint64(64) - r))


# Positional on purpose: a numba kernel takes plain arrays and scalars (no records, no keyword defaults).
@njit(nogil=True, cache=True)
def mtb_band_counts(grey_a, grey_b, med_a, med_b, exclusion, starts, band, margin, cand_y, cand_x,
                    out):  # pragma: no cover - compiled
    """Ward's MTB scores on bands of rows (:func:`derender.engine.motion.ward2003._mtb_counts_bands`), from the greys.

    For every candidate shift ``c`` adds to ``out[c, 0]`` the pixels whose threshold bits
    (``g > med``) differ and to ``out[c, 1]`` the pixels outside both exclusion bitmaps
    (``|g - med| > exclusion``), over reference rows ``s .. s + band - 1`` (below the image
    height) of every start ``s``, comparing reference pixel ``(y, x)`` with image pixel
    ``(y + cand_y[c], x + cand_x[c])`` where that is inside the image. Rows are packed 64
    pixels per word, once per band for each image; a horizontal shift of the image moves
    its packed words (:func:`_shift_words`) instead of packing its pixels again (measured on
    the 24 MP bracket, one thread: the kernel 0.41-0.49 -> 0.18 s,
    the whole MTB 0.8-1.1 -> 0.67 s); ``margin >= max |cand_y|``.
    """
    h, w = grey_a.shape
    nw = (w + 63) // 64
    lo_a, hi_a = med_a - exclusion, med_a + exclusion
    lo_b, hi_b = med_b - exclusion, med_b + exclusion
    ta = np.zeros((band, nw), dtype=np.uint64)
    ea = np.zeros((band, nw), dtype=np.uint64)
    rb = band + 2 * margin
    pb_t = np.zeros((rb, nw), dtype=np.uint64)     # image rows packed unshifted
    pb_e = np.zeros((rb, nw), dtype=np.uint64)
    tb = np.zeros((rb, nw), dtype=np.uint64)       # ... shifted by the candidate's x
    eb = np.zeros((rb, nw), dtype=np.uint64)
    done = np.zeros(cand_x.shape[0], dtype=np.bool_)
    for s in starts:
        for r in range(band):
            if s + r < h:
                _pack_row(grey_a, s + r, 0, med_a, lo_a, hi_a, ta[r], ea[r])
            else:
                ta[r, :] = 0
                ea[r, :] = 0
        for rr in range(rb):
            y = s - margin + rr
            if 0 <= y < h:
                _pack_row(grey_b, y, 0, med_b, lo_b, hi_b, pb_t[rr], pb_e[rr])
            else:
                pb_t[rr, :] = 0
                pb_e[rr, :] = 0
        done[:] = False
        for c0 in range(cand_x.shape[0]):
            if done[c0]:
                continue
            sx = cand_x[c0]
            for rr in range(rb):
                _shift_words(pb_t[rr], sx, tb[rr])
                _shift_words(pb_e[rr], sx, eb[rr])
            for c in range(c0, cand_x.shape[0]):
                if done[c] or cand_x[c] != sx:
                    continue
                done[c] = True
                off = margin + cand_y[c]
                nd = np.uint64(0)
                nb = np.uint64(0)
                for r in range(band):
                    for k in range(nw):
                        both = ea[r, k] & eb[r + off, k]
                        nb += _popcount64(both)
                        nd += _popcount64((ta[r, k] ^ tb[r + off, k]) & both)
                out[c, 0] += np.int64(nd)
                out[c, 1] += np.int64(nb)


# Positional on purpose: a numba kernel takes plain arrays and scalars (no records, no keyword defaults).
@njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def table_merge_rows(frames, valid, ref, order, values, weights, independent, log_domain, v_short, v_long, j_short,
                     j_long, bright, y0, y1, row0, out, mask):  # pragma: no cover - compiled
    """Rows ``y0:y1`` of the table merge (:class:`derender.engine.tables.TableMerge`, modes
    ``"mean"`` and ``"independent"``) of held frames in one pass per pixel, same arithmetic.

    ``frames`` (N, H, W, 3) uint8; frame ``j`` takes part where ``valid[j, y, x]`` (``valid`` of
    shape (N, 1, 1): everywhere; the engine's alignment and ghost removal,
    :mod:`derender.engine.motion`); frames are added in the order ``order``; frame ``j``'s code
    ``z`` of channel ``c`` contributes ``values[j, z, c]`` with weight ``weights[j, z, c]``
    (float32, already scaled by the image weight, and by 1/3 in the ``"mean"`` mode, as
    :meth:`TableMerge.add` scales them). ``"mean"`` (``independent`` False): one weight per
    pixel, the float32 sum ``(w0 + w1) + w2``; ``"independent"``: one per channel. In the log
    domain the sums are float64 (``den += w``, ``num += v * w``: a float32 product is exact in
    float64), in the linear one float32 with OpenCV's fused multiply-add (``accumulateProduct``;
    the float64 product rounded once), as the table engine keeps them. Where a channel's
    weights sum to 0 its value comes from the shortest exposure (``j_short``, table
    ``v_short``) if ``bright[code]`` (the ``"mean"`` mode: the channel's code, like the
    engine's finish), else from the longest; where frames are left out (``valid``, ``ref >= 0``
    the reference frame) the reference's code decides, and the value comes from the shortest
    frame taking part that is bright there, else the longest that is not; ``mask`` 1 if some channel took the shortest,
    else 2 if some took the longest, else 0. ``out`` (3, rows, W) float32 receives row ``y``'s
    value at ``out[:, y - row0]`` (the whole image: ``row0`` 0; a band buffer: its first row)
    (log domain: ``min(value, 88)``, to be exponentiated by the caller with OpenCV on the
    engine's blocks; linear: non-finite values replaced as ``np.nan_to_num``).
    """
    n = order.shape[0]
    nf = frames.shape[0]
    w = frames.shape[2]
    whole = valid.shape[1] == 1 and valid.shape[2] == 1
    tile = MERGE_TILE
    f32max = np.float32(3.4028234663852886e38)
    for y in prange(y0, y1):
        num64 = np.zeros((3, tile), dtype=np.float64)
        den64 = np.zeros((3, tile), dtype=np.float64)
        num32 = np.zeros((3, tile), dtype=np.float32)
        den32 = np.zeros((3, tile), dtype=np.float32)
        for x0 in range(0, w, tile):
            xe = min(x0 + tile, w)
            num64[:, :] = 0.0
            den64[:, :] = 0.0
            num32[:, :] = 0.0
            den32[:, :] = 0.0
            for k in range(n):
                j = order[k]
                for x in range(x0, xe):
                    if not whole and valid[j, y, x] == 0:
                        continue
                    add_table_observation(frames, j, y, x, x - x0, weights, values, independent, log_domain,
                                           num64, den64, num32, den32)
            for x in range(x0, xe):
                t = x - x0
                nb = False
                ndk = False
                for c in range(3):
                    dc = c if independent else 0
                    if log_domain:
                        ok = den64[dc, t] > 0.0
                        r = num64[c, t] / den64[dc, t] if ok else 0.0
                    else:
                        ok = den32[dc, t] > np.float32(0.0)
                        r = np.float64(num32[c, t] / den32[dc, t]) if ok else 0.0
                    if not ok and (whole or ref < 0):
                        zs = frames[j_short, y, x, c]
                        if bright[zs]:
                            r = np.float64(v_short[zs, c])
                            nb = True
                        else:
                            r = np.float64(v_long[frames[j_long, y, x, c], c])
                            ndk = True
                    elif not ok:
                        # frames left out here: the reference's code decides, the tightest bound
                        # on its side among the frames taking part gives the value
                        up = bright[frames[ref, y, x, c]]
                        jj = ref
                        for k in range(nf):
                            jv = k if up else nf - 1 - k
                            if valid[jv, y, x] != 0 and bright[frames[jv, y, x, c]] == up:
                                jj = jv
                                break
                        r = np.float64(values[jj, frames[jj, y, x, c], c])
                        if up:
                            nb = True
                        else:
                            ndk = True
                    if log_domain:
                        out[c, y - row0, x] = np.float32(min(r, 88.0))
                    else:
                        o = np.float32(r)
                        if np.isnan(o):
                            o = np.float32(0.0)
                        elif o > f32max:
                            o = f32max
                        elif o < -f32max:
                            o = -f32max
                        out[c, y - row0, x] = o
                mask[y, x] = 1 if nb else (2 if ndk else 0)


# Positional on purpose: a numba kernel takes plain arrays and scalars (no records, no keyword defaults).
@njit(nogil=True, cache=True)
def gaussian_band(frames, valid, lut, planes, log_scales, y0, y1, prec, acc, bound):  # pragma: no cover - compiled
    """Rows ``y0:y1`` of the log-space Gaussian product (:class:`derender.engine.gaussian.LogGaussianProduct`)
    of held frames (N, H, W, 3) uint8 (frame ``j`` where ``valid[j, y, x]``; ``valid`` (N, 1, 1):
    everywhere), in one pass per pixel: the colour's row is
    ``lut[R << 16 | G << 8 | B]`` (:class:`derender.derendering.apply.ColourIndex`), ``planes``
    (9, M) float64 ``[mu; p; low]`` per channel; frame ``j`` (in order) adds ``p``,
    ``(mu + s_j) p`` and ``max(bound, low + s_j)`` per channel into ``prec``, ``acc``, ``bound``
    (3, y1 - y0, W) float64 (initialised by the caller: 0, 0, -inf). The float64 operations and
    their order per pixel are :meth:`LogGaussianProduct.add_rows`'s, so the sums are the same
    bytes. Row by row (the row's sums stay in cache across the frames); releases the GIL.
    Reading the planes colour-major, (M, 9), was no faster (measured: 0.38-0.41 against
    0.42-0.43 CPU s per 640 x 3000 x 9 frames) and a transposed copy costs 72 bytes per
    distinct colour and 0.7 s; the probabilistic merge now writes a colour-major (M, 8) table
    directly, one cache line per colour, and runs :func:`gaussian_moments_band` instead
    (65 -> 43 ms per 64 rows x 9 frames of the 24 MP bracket)."""
    n = frames.shape[0]
    w = frames.shape[2]
    whole = valid.shape[1] == 1 and valid.shape[2] == 1
    for y in range(y0, y1):
        r = y - y0
        for j in range(n):
            ls = log_scales[j]
            for x in range(w):
                if not whole and valid[j, y, x] == 0:
                    continue
                k = lut[(np.int64(frames[j, y, x, 0]) << 16) | (np.int64(frames[j, y, x, 1]) << 8)
                        | np.int64(frames[j, y, x, 2])]
                for c in range(3):
                    p = planes[3 + c, k]
                    prec[c, r, x] += p
                    acc[c, r, x] += (planes[c, k] + ls) * p
                    b = planes[6 + c, k] + ls
                    if b > bound[c, r, x]:
                        bound[c, r, x] = b


@njit(inline="always")
def normal_cdf(a):  # pragma: no cover - compiled
    """Standard normal CDF, the algorithm of cephes' (SciPy's) ``ndtr`` on libm's erf / erfc."""
    x = a * 0.7071067811865476
    z = abs(x)
    if z < 0.7071067811865476:
        return 0.5 + 0.5 * math.erf(x)
    y = 0.5 * math.erfc(z)
    return 1.0 - y if x > 0.0 else y


# Positional on purpose: a numba kernel takes plain arrays and scalars (no records, no keyword defaults).
@njit(nogil=True, cache=True, error_model="numpy")
def gaussian_moments_band(frames, valid, lut, table, log_scales, y0, y1, censor, max_log, max_v, a, use_a,
                          row0, radiance, variance):  # pragma: no cover - compiled
    """Rows ``y0:y1`` of the log-space Gaussian product, sums and moments in one pass: the sums of
    :func:`gaussian_band` (same float64 operations and order), kept for one row at a time, from a
    colour-major table (M, 8) ``[mu (3), p, low (3), 0]`` per colour (channel ``c``'s precision
    is ``p`` where ``low_c`` is ``-inf``, else 0; one 64-byte cache line per colour where
    :func:`gaussian_band`'s planes take nine: measured 65 -> 43 ms per 64 rows x 9 frames of
    the 24 MP bracket), then
    per pixel and channel what :func:`derender.hdr.probabilistic.log_product_moments` and
    :func:`derender.hdr.probabilistic.finite_outputs` compute from them: ``v = 1 / prec``,
    ``m = acc v`` (``inf``, 0 where ``prec`` is 0); with ``censor`` the truncated-normal
    moments below ``bound`` (:func:`derender.hdr.lognormal.truncate_below_log`); ``m`` clipped to ``+-max_log``, ``v`` to
    ``[0, max_v]``; raw moments ``e = exp(m + v/2)``, ``expm1(v) e^2``; through ``a`` (3x3,
    camera -> output, variance by ``a * a``) if ``use_a``; the mean projected onto ``>= 0`` (a
    projected channel's variance plus its squared distance, as ``finite_outputs``); clipped to ``f32max/4`` and written
    as float32 into ``radiance`` and ``variance`` (rows, W, 3), row ``y`` at index ``y - row0``
    (the whole image: ``row0`` 0; band buffers: the band's first row). Releases the GIL."""
    n = frames.shape[0]
    w = frames.shape[2]
    whole = valid.shape[1] == 1 and valid.shape[2] == 1
    prec = np.empty((3, w))
    acc = np.empty((3, w))
    bound = np.empty((3, w))
    big = np.float64(np.finfo(np.float32).max) / 4.0
    inf = np.inf
    rs2pi = 1.0 / math.sqrt(2.0 * math.pi)
    mean0 = np.empty(3)
    var0 = np.empty(3)
    for y in range(y0, y1):
        prec[:, :] = 0.0
        acc[:, :] = 0.0
        bound[:, :] = -inf
        for j in range(n):
            ls = log_scales[j]
            for x in range(w):
                if not whole and valid[j, y, x] == 0:
                    continue
                k = lut[(np.int64(frames[j, y, x, 0]) << 16) | (np.int64(frames[j, y, x, 1]) << 8)
                        | np.int64(frames[j, y, x, 2])]
                pj = table[k, 3]
                for c in range(3):
                    lo = table[k, 4 + c]
                    p = pj if lo == -inf else 0.0
                    prec[c, x] += p
                    acc[c, x] += (table[k, c] + ls) * p
                    b = lo + ls
                    if b > bound[c, x]:
                        bound[c, x] = b
        for x in range(w):
            for c in range(3):
                pr = prec[c, x]
                if pr > 0.0:
                    v = 1.0 / pr
                    m = acc[c, x] * v
                else:
                    v = inf
                    m = 0.0
                if censor:
                    bd = bound[c, x]
                    active = np.isfinite(bd)
                    finite = np.isfinite(v)
                    om = m
                    ov = v
                    if active and finite:
                        sd = math.sqrt(v)
                        alpha = (bd - m) / max(sd, 1e-300)
                        if alpha < 3.0 and alpha > -8.0:
                            tail = max(1.0 - normal_cdf(alpha), 1e-300)
                            lam = math.exp(-0.5 * alpha * alpha) * rs2pi / tail
                            om = m + sd * lam
                            ov = v * max(1.0 + alpha * lam - lam * lam, 1e-6)
                    elif active:
                        om = bd - 0.5
                        ov = 1.0
                    if not (np.isfinite(ov) and np.isfinite(om)):
                        om = -max_log
                        ov = 1.0
                    m = om
                    v = ov
                m = min(max(m, -max_log), max_log)
                v = min(max(v, 0.0), max_v)
                e = math.exp(m + 0.5 * v)
                mean0[c] = e
                var0[c] = math.expm1(v) * (e * e)     # exp(2m + v) within an ulp, one exp less
            for c in range(3):
                if use_a:
                    mo = mean0[0] * a[c, 0] + mean0[1] * a[c, 1] + mean0[2] * a[c, 2]
                    vo = var0[0] * (a[c, 0] * a[c, 0]) + var0[1] * (a[c, 1] * a[c, 1]) + var0[2] * (a[c, 2] * a[c, 2])
                else:
                    mo = mean0[c]
                    vo = var0[c]
                if np.isnan(mo):
                    mo = 0.0
                if mo < 0.0:          # projected onto the non-negative orthant (finite_outputs)
                    vo = vo + mo * mo
                    mo = 0.0
                radiance[y - row0, x, c] = np.float32(min(mo, big))
                if np.isnan(vo):
                    vo = big
                variance[y - row0, x, c] = np.float32(min(max(vo, 0.0), big))


@njit(inline="always")
def table_mu(tab, lut_lo, lut_w, c0, c1, c2, ch):  # pragma: no cover - compiled
    """Channel ``ch`` of :meth:`derender.derendering.log_space.LatentTable.at_codes` at one colour
    (float32 linear interpolation along R of the G/B-interpolated table, as float64)."""
    j = np.int64(lut_lo[c0]) * 65536 + np.int64(c1) * 256 + np.int64(c2)
    v0 = tab[j, ch]
    v1 = tab[j + 65536, ch]
    return np.float64((v1 - v0) * lut_w[c0] + v0)


@njit(inline="always")
def _log_median(m, eps, max_log):  # pragma: no cover - compiled
    """``log(max(exp(m) - eps, 1e-30))`` of a log mean ``m`` (NaN -> 0, clipped to +-max_log)."""
    if np.isnan(m):
        m = 0.0
    m = min(max(m, -max_log), max_log)
    return math.log(max(math.exp(m) - eps, 1e-30))


# Positional on purpose: a numba kernel takes plain arrays and scalars (no records, no keyword defaults).
@njit(nogil=True, cache=True, error_model="numpy")
def log_tables_rows(colours, s0, s1, tab_mu, tab_lv, lut_lo, lut_w, eps, floor, clip_code, censor, per_channel,
                    code_noise, step, bound_sigmas, max_log, planes, colour_major):  # pragma: no cover - compiled
    """Columns ``s0:s1`` of the probabilistic merge's per-colour planes (9, M) ``[lg; p; low]``
    (:func:`derender.hdr.probabilistic._log_tables` with :func:`~derender.hdr.probabilistic._log_slope`)
    for (M, 3) uint8 ``colours``, read from a GP's interpolation table (``tab_mu``, ``tab_lv``:
    the float32 G/B tables of :class:`~derender.derendering.log_space.LatentTable`, ``lut_lo`` /
    ``lut_w`` (float32) its R nodes and weights): the same operations, colour by colour, in
    float64 after the float32 interpolation. With ``colour_major`` ``planes`` is instead the
    (M, 8) table of :func:`gaussian_moments_band`: ``[lg (3), p, low (3), 0]`` per colour, ``p``
    the joint precision of the measured channels (a channel's precision is ``p`` where its
    ``low`` is ``-inf``, else 0: the same values as the planes). Releases the GIL."""
    tiny = 1e-30
    lg = np.empty(3)
    s2l = np.empty(3)
    low = np.empty(3)
    clipped = np.empty(3, dtype=np.bool_)
    cc = np.empty(3, dtype=np.int64)
    for i in range(s0, s1):
        for ch in range(3):
            cc[ch] = np.int64(colours[i, ch])
        any_clipped = False
        for ch in range(3):
            clipped[ch] = censor and cc[ch] >= clip_code
            any_clipped = any_clipped or clipped[ch]
        if not per_channel:
            for ch in range(3):
                clipped[ch] = any_clipped
        for ch in range(3):
            mu = table_mu(tab_mu, lut_lo, lut_w, cc[0], cc[1], cc[2], ch)
            s2 = math.exp(table_mu(tab_lv, lut_lo, lut_w, cc[0], cc[1], cc[2], ch))
            if np.isnan(mu):
                mu = 0.0
            mu = min(max(mu, -max_log), max_log)
            if np.isnan(s2):
                s2 = 1e6
            s2 = min(max(s2, 1e-12), 1e6)
            e = math.exp(mu)
            r = max(e - eps, tiny)
            lg[ch] = math.log(r)
            q = e / r
            v = min(s2 * (q * q), 1e6) + floor
            if code_noise > 0:
                up = min(cc[ch] + step, 255)
                dn = max(cc[ch] - step, 0)
                if ch == 0:
                    mu_u = table_mu(tab_mu, lut_lo, lut_w, up, cc[1], cc[2], 0)
                    mu_d = table_mu(tab_mu, lut_lo, lut_w, dn, cc[1], cc[2], 0)
                elif ch == 1:
                    mu_u = table_mu(tab_mu, lut_lo, lut_w, cc[0], up, cc[2], 1)
                    mu_d = table_mu(tab_mu, lut_lo, lut_w, cc[0], dn, cc[2], 1)
                else:
                    mu_u = table_mu(tab_mu, lut_lo, lut_w, cc[0], cc[1], up, 2)
                    mu_d = table_mu(tab_mu, lut_lo, lut_w, cc[0], cc[1], dn, 2)
                slope = (_log_median(mu_u, eps, max_log) - _log_median(mu_d, eps, max_log)) / np.float64(
                    max(up - dn, 1))
                t = code_noise * slope
                v = min(v + t * t, 1e6)
            s2l[ch] = v
            if clipped[ch]:
                low[ch] = math.log(max(math.exp(mu - bound_sigmas * math.sqrt(s2)) - eps, tiny))
            else:
                low[ch] = -np.inf
        n_ok = 0
        tot = 0.0
        for ch in range(3):
            if not clipped[ch]:
                n_ok += 1
                tot += s2l[ch]
        pj = 1.0 / max(tot / np.float64(max(n_ok, 1)), 1e-12)
        if colour_major:
            for ch in range(3):
                planes[i, ch] = lg[ch]
                planes[i, 4 + ch] = low[ch]
            planes[i, 3] = pj
            planes[i, 7] = 0.0
            continue
        for ch in range(3):
            planes[ch, i] = lg[ch]
            planes[3 + ch, i] = 0.0 if (clipped[ch] or n_ok == 0) else pj
            planes[6 + ch, i] = low[ch]


@njit(nogil=True, cache=True)
def mark_colours(frames, j0, j1, present):  # pragma: no cover - compiled
    """``present[R << 16 | G << 8 | B] = True`` for every pixel of frames ``j0:j1`` of
    (N, H, W, 3) uint8 (a presence bitmap over the 2**24 colours, as
    :class:`derender.derendering.apply.ColourIndexBuilder` fills it). Releases the GIL; two
    threads may mark the same bitmap (they only ever store True)."""
    h, w = frames.shape[1], frames.shape[2]
    for j in range(j0, j1):
        for y in range(h):
            for x in range(w):
                present[(np.int64(frames[j, y, x, 0]) << 16) | (np.int64(frames[j, y, x, 1]) << 8)
                        | np.int64(frames[j, y, x, 2])] = True
