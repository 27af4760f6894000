"""The table engine: 8-bit exposures merged by 256-entry look-up tables, in row blocks, in threads.

An 8-bit image has 256 code values per channel, so every per-channel linearisation
(Debevec & Malik 1997, eq. 6: ``g(z) - ln t_j``; or ``f^-1(z) / t_j`` in the linear
domain) and every weight ``w(z)`` is a 256-entry table per channel and exposure. The
merge then becomes table look-ups and multiply-adds into float64 (log domain) or float32
accumulators (OpenCV's ``LUT``, ``accumulate`` and ``accumulateProduct``, which release
the GIL), run on blocks of rows by a thread pool.

* :class:`TableMerge` -- ``add(codes, values, weights)`` per exposure, ``finish()``
  applies the saturation policy exactly as :func:`~derender.engine.float_merge.merge_linear`
  and returns an :class:`~derender.core.types.HDRResult`. An optional per-image 3x3
  matrix is applied to the linearised values per block.
* :func:`merge_codes` -- the table merge of in-memory 8-bit exposures.
* :func:`merge_curves_table` -- the table path for an in-memory 8-bit stack and
  per-channel response curves; ``None`` when the stack is not 8-bit.

Results equal the reference engine to about 1e-6 relative (the value tables are float32;
tested to 1e-5).
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from derender.core.errors import InputError
from derender.core.memory import N_CODES, import_cv2, opencv_single_thread, populated_zeros, thread_count
from derender.core.types import HDRResult, Stack
from derender.engine.weights import F32_MAX

__all__ = [
    "code_histograms",
    "code_table",
    "code_values",
    "weight_table",
    "curve_value_tables",
    "stack_codes_exact",
    "TableMerge",
    "merge_codes",
    "merge_curves_table",
]


def code_values() -> np.ndarray:
    """The 256 normalised values of 8-bit codes, float32 ``k * float32(1/255)`` (as :func:`derender.io.read_image`)."""
    return np.arange(N_CODES, dtype=np.float32) * np.float32(1.0 / 255.0)


def weight_table(weight: str | Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """(256, 3) float32 table of a weight (name in :data:`~derender.engine.weights.WEIGHTS` or pointwise callable) on the codes."""
    from derender.engine.weights import get_weight

    fn = get_weight(weight)
    z = np.repeat(code_values()[:, None], 3, axis=1)
    w = np.asarray(fn(z), dtype=np.float32)
    if w.shape == (N_CODES,):
        w = np.repeat(w[:, None], 3, axis=1)
    if w.shape != (N_CODES, 3):
        raise InputError(f"weight function returned shape {w.shape} for (256, 3) codes")
    return np.ascontiguousarray(w)


def curve_value_tables(curves, times: Any, domain: str = "log") -> np.ndarray:
    """(N, 256, 3) float32: the value each code contributes for exposure ``j`` (merge_linear, eq. 6).

    ``domain="log"``: ``g(z) - ln t_j``; ``"linear"``: ``exp(g(z) - ln t_j)``, with
    ``g`` from :meth:`ResponseCurves.log_linearise` evaluated on the code values (the
    same float32 interpolation the reference applies to every pixel).
    """
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    g = curves.log_linearise(np.repeat(code_values()[:, None], 3, axis=1)).astype(np.float64)
    v = g[None] - np.log(t)[:, None, None]
    if domain == "linear":
        v = np.exp(v)
    elif domain != "log":
        raise InputError(f"domain must be 'linear' or 'log', got {domain!r}")
    return np.ascontiguousarray(v, dtype=np.float32)


def stack_codes_exact(images: np.ndarray, tol: float = 1e-3) -> np.ndarray | None:
    """uint8 codes of an (N, H, W, 3) float stack in [0, 1] if every value is ``code / 255`` (to ``tol`` codes), else None.

    Works on blocks of rows (small temporaries: large fresh ones cost page faults).
    """
    images = np.asarray(images)
    if images.dtype == np.uint8:
        return images
    if images.ndim != 4 or images.dtype.kind != "f":
        return None
    n, h, w = images.shape[:3]
    out = np.empty(images.shape, dtype=np.uint8)
    rows = max(1, (1 << 16) // max(w, 1))
    x = np.empty((rows, w, 3), dtype=np.float32)
    r = np.empty_like(x)
    for j in range(n):
        for r0 in range(0, h, rows):
            r1 = min(h, r0 + rows)
            xb, rb = x[: r1 - r0], r[: r1 - r0]
            np.multiply(images[j, r0:r1], np.float32(255.0), out=xb, casting="unsafe")
            np.rint(xb, out=rb)
            if rb.min() < 0 or rb.max() > 255:
                return None
            np.subtract(xb, rb, out=xb)
            np.abs(xb, out=xb)
            if xb.max() > tol:
                return None
            out[j, r0:r1] = rb
    return out


# --------------------------------------------------------------------------- engine
_ENGINE_MODES = ("mean", "min", "independent", "brightest", "min_else_brightest")


def code_table(t: Any, what: str) -> np.ndarray:
    """A per-code table as (256, 3) float32 (a (256,) table shared by the channels); an
    :class:`InputError` naming ``what`` for another shape or a non-finite entry."""
    t = np.asarray(t, dtype=np.float32)
    if t.shape == (N_CODES,):
        t = np.repeat(t[:, None], 3, axis=1)
    if t.shape != (N_CODES, 3):
        raise InputError(f"{what} table must have shape (256, 3), got {t.shape}")
    if not np.all(np.isfinite(t)):
        raise InputError(f"{what} table has non-finite entries")
    return t


@dataclass(frozen=True)
class _ExposureTables:
    """One exposure's look-up tables, laid out for ``cv2.LUT``, and its optional per-pixel factors."""

    values: list          # 3 float32 (256,) columns: v_j(z) per channel (linearisation when a matrix is given)
    weights: list         # 3 float32 (256,) columns: w(z) * image_weight (/3 for "mean")
    matrix: np.ndarray | None         # (3, 3) float64 colour matrix, linear domain only
    pixel_weights: np.ndarray | None  # (H, W) float32
    inverse_variance: tuple | None    # (3 float32 (256,) columns of table / 3, k)


def _accumulate(cv2: Any, dst: np.ndarray, a: np.ndarray, b: np.ndarray | None = None) -> None:
    """dst += a (* b), float32 sources into a float32 or float64 accumulator."""
    if b is None:
        cv2.accumulate(a, dst)
    else:
        cv2.accumulateProduct(a, b, dst)


def _block_values(cv2: Any, p: Sequence[np.ndarray], tables: _ExposureTables) -> list:
    """The averaged value planes of a block's code planes ``p``: ``v(z)``, or ``matrix @ lin(z)``."""
    vcol, m = tables.values, tables.matrix
    if m is None:
        return [cv2.LUT(p[c], vcol[c]) for c in range(3)]
    lin = [cv2.LUT(p[d], vcol[d]) for d in range(3)]
    vals = []
    for c in range(3):
        v = cv2.addWeighted(lin[0], float(m[c, 0]), lin[1], float(m[c, 1]), 0.0)
        cv2.scaleAdd(lin[2], float(m[c, 2]), v, dst=v)
        vals.append(v)
    return vals


def _block_inverse_variance(cv2: Any, p: Sequence[np.ndarray], ivt: tuple | None) -> np.ndarray | None:
    """``k / max(mean_c table[z_c, c], 1e-30)`` per pixel of a block, or None."""
    if ivt is None:
        return None
    d = cv2.add(cv2.LUT(p[0], ivt[0][0]), cv2.LUT(p[1], ivt[0][1]))
    cv2.add(d, cv2.LUT(p[2], ivt[0][2]), dst=d)
    np.maximum(d, np.float32(1e-30), out=d)
    return cv2.divide(ivt[1], d)


def _block_weights(cv2: Any, mode: str, p: Sequence[np.ndarray], tables: _ExposureTables,
                   r0: int, r1: int) -> tuple:
    """Per-channel weight planes of one weight set for a block (a tuple of 3, possibly the same plane)."""
    wcol, pw = tables.weights, tables.pixel_weights
    if mode == "independent":
        wc = [cv2.LUT(p[c], wcol[c]) for c in range(3)]
        if pw is not None:
            for c in range(3):
                cv2.multiply(wc[c], pw[r0:r1], dst=wc[c])
        return tuple(wc)
    if mode == "brightest":
        wsum = cv2.LUT(cv2.max(cv2.max(p[0], p[1]), p[2]), wcol[0])
    else:
        w0, w1, w2 = (cv2.LUT(p[c], wcol[c]) for c in range(3))
        if mode == "mean":
            wsum = cv2.add(w0, w1)
            cv2.add(wsum, w2, dst=wsum)
        else:
            wsum = cv2.min(w0, w1)
            cv2.min(wsum, w2, dst=wsum)
    if pw is not None:
        cv2.multiply(wsum, pw[r0:r1], dst=wsum)
    return (wsum, wsum, wsum)


class TableMerge:
    """Weighted merge of 8-bit exposures by table look-up (Debevec & Malik 1997, eq. 6), in row blocks.

    ``add(codes, values, weights)`` accumulates one exposure: ``codes`` (H, W, 3)
    uint8 RGB, ``values`` (256, 3) the per-channel value ``v_j(z)`` of each code (what
    :func:`~derender.engine.float_merge.merge_linear` averages: ``g(z) - ln t_j`` in the log domain,
    ``lin(z) / t_j`` in the linear one), ``weights`` (256, 3) ``w(z)``. With ``matrix``
    (3, 3), ``values`` is a per-channel linearisation and the averaged value is
    ``matrix @ values(z)`` (linear domain only). ``image_weight`` multiplies the weights
    and ``pixel_weights`` ((H, W), e.g. a registration mask) multiplies them per pixel.

    ``channel_weights``: ``"mean"``, ``"min"`` or ``"independent"`` as in merge_linear;
    ``"brightest"``: every channel takes the weight of the pixel's largest code, and
    the saturation policy judges that code too; ``"min_else_brightest"``: the ``"min"``
    weights where some exposure has all channels usable, else the ``"brightest"`` ones
    (two sets of accumulators; the weights of the stabilised merge of paper 1, whose
    compiled form is :func:`merge_stabilized_table`). :meth:`finish` needs the codes and
    tables of the shortest and longest exposures for the saturation policy.

    Accumulators: float64 in the log domain (a float32 sum of ``w (g - ln t)`` would
    lose up to ``N * 6e-8 * |ln E|`` relative, ~1e-5 for 18 frames), float32 in the
    linear domain (sums of same-sign terms); ``accumulator`` overrides. The float32
    radiance is written in place into the accumulator memory, so a merge needs
    8 (or 16) bytes per pixel and channel plus the weight planes, and nothing more.
    """

    def __init__(self, shape: tuple[int, int], channel_weights: str = "mean", domain: str = "log",
                 bright_threshold: float = 0.5, threads: int | None = None, block_rows: int | None = None,
                 accumulator: str = "auto"):
        if channel_weights not in _ENGINE_MODES:
            raise InputError(f"channel_weights must be one of {', '.join(_ENGINE_MODES)}, got {channel_weights!r}")
        if domain not in ("linear", "log"):
            raise InputError(f"domain must be 'linear' or 'log', got {domain!r}")
        if accumulator not in ("auto", "float32", "float64"):
            raise InputError(f"accumulator must be 'auto', 'float32' or 'float64', got {accumulator!r}")
        if accumulator == "auto":
            accumulator = "float64" if domain == "log" else "float32"
        h, w = int(shape[0]), int(shape[1])
        self.shape = (h, w)
        self.mode = channel_weights
        self.domain = domain
        self.bright_threshold = float(bright_threshold)
        self.threads = thread_count(threads)
        if block_rows is None:
            block_rows = max(1, (1 << 16) // max(w, 1))
        self.block_rows = max(1, int(block_rows))
        self.dtype = np.dtype(accumulator)
        self.sets = ("min", "brightest") if channel_weights == "min_else_brightest" else (channel_weights,)
        self.num = populated_zeros((3 * len(self.sets), h, w), dtype=self.dtype)
        self.den = populated_zeros(((3 if channel_weights == "independent" else 1) * len(self.sets), h, w),
                                   dtype=self.dtype)
        self.n_added = 0
        self._pool: ThreadPoolExecutor | None = None

    # -- threading
    def _bands(self) -> list[tuple[int, int]]:
        h = self.shape[0]
        step = self.block_rows * 8
        return [(r0, min(h, r0 + step)) for r0 in range(0, h, step)]

    def _run(self, fn: Callable[[int, int], Any]) -> list:
        """``fn(r0, r1)`` over bands of rows. OpenCV's own threads are off meanwhile: ours own the
        cores, and OpenCV's split of an array (SIMD body vs scalar tail, e.g. in ``exp``) must not
        depend on its thread count, so the bytes of a result never depend on the machine."""
        bands = self._bands()
        with opencv_single_thread():
            if self.threads == 1 or len(bands) == 1:
                return [fn(a, b) for a, b in bands]
            if self._pool is None:
                self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="derender-merge")
            return list(self._pool.map(lambda ab: fn(*ab), bands))

    def close(self) -> None:
        """Stop the worker threads."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def __enter__(self) -> "TableMerge":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- accumulate
    def _check_codes(self, codes: np.ndarray) -> np.ndarray:
        codes = np.asarray(codes)
        if codes.dtype != np.uint8 or codes.shape != (*self.shape, 3):
            raise InputError(f"codes must be uint8 of shape {(*self.shape, 3)}, got {codes.dtype} {codes.shape}")
        return np.ascontiguousarray(codes)

    def add(self, codes: np.ndarray, values: Any, weights: Any, image_weight: float = 1.0,
            matrix: Any = None, pixel_weights: np.ndarray | None = None,
            inverse_variance: tuple[Any, float] | None = None) -> None:
        """Accumulate one exposure (see the class docstring).

        ``inverse_variance=(table, k)`` further multiplies every weight of a pixel by
        ``k / max(mean_c table[z_c, c], 1e-30)`` (e.g. ``t_j^2 / mean (dL/dJ)^2``: the
        inverse variance of the radiance estimate for equal code noise).
        """
        cv2 = import_cv2()
        codes = self._check_codes(codes)
        tables = self._exposure_tables(values, weights, image_weight, matrix, pixel_weights, inverse_variance)
        br = self.block_rows

        def band(b0: int, b1: int) -> None:
            for r0 in range(b0, b1, br):
                r1 = min(b1, r0 + br)
                self._accumulate_block(cv2, codes, tables, r0, r1)

        self._run(band)
        self.n_added += 1

    def _exposure_tables(self, values: Any, weights: Any, image_weight: float, matrix: Any,
                         pixel_weights: np.ndarray | None,
                         inverse_variance: tuple[Any, float] | None) -> _ExposureTables:
        """Check one exposure's inputs and lay out its per-channel look-up tables for ``cv2.LUT``."""
        vt = code_table(values, "value")
        wt = code_table(weights, "weight").astype(np.float64) * float(image_weight)
        if self.mode == "mean":
            wt = wt / 3.0
        wt = wt.astype(np.float32)
        vcol = [np.ascontiguousarray(vt[:, c]) for c in range(3)]
        wcol = [np.ascontiguousarray(wt[:, c]) for c in range(3)]
        m = None
        if matrix is not None:
            if self.domain != "linear":
                raise InputError("a colour matrix needs the linear domain")
            m = np.asarray(matrix, dtype=np.float64)
            if m.shape != (3, 3) or not np.all(np.isfinite(m)):
                raise InputError(f"matrix must be a finite 3x3 array, got shape {m.shape}")
        pw = None
        if pixel_weights is not None:
            pw = np.asarray(pixel_weights)
            if pw.shape != self.shape:
                raise InputError(f"pixel_weights must have shape {self.shape}, got {pw.shape}")
            pw = np.ascontiguousarray(pw, dtype=np.float32)
        ivt = None
        if inverse_variance is not None:
            itab = code_table(inverse_variance[0], "inverse-variance")
            ivt = ([np.ascontiguousarray(itab[:, c] / np.float32(3.0)) for c in range(3)], float(inverse_variance[1]))
        return _ExposureTables(vcol, wcol, m, pw, ivt)

    def _accumulate_block(self, cv2: Any, codes: np.ndarray, tables: _ExposureTables, r0: int, r1: int) -> None:
        """Add rows ``r0:r1`` of one exposure into every weight set's accumulators."""
        p = cv2.split(codes[r0:r1])
        vals = _block_values(cv2, p, tables)
        inv = _block_inverse_variance(cv2, p, tables.inverse_variance)
        nd = 3 if self.mode == "independent" else 1
        num, den = self.num, self.den
        for k, smode in enumerate(self.sets):
            wc = _block_weights(cv2, smode, p, tables, r0, r1)
            if inv is not None:
                wc = tuple(cv2.multiply(x, inv) for x in wc) if wc[0] is not wc[1] else \
                    (cv2.multiply(wc[0], inv),) * 3
            for i in range(nd):
                _accumulate(cv2, den[k * nd + i, r0:r1], wc[i])
            for c in range(3):
                _accumulate(cv2, num[k * 3 + c, r0:r1], vals[c], wc[c])

    # -- finish
    @staticmethod
    def _values_at(z: np.ndarray, vt: np.ndarray, matrix: Any) -> np.ndarray:
        v = np.stack([vt[z[:, c], c] for c in range(3)], axis=1).astype(np.float64)
        if matrix is not None:
            v = v @ np.asarray(matrix, dtype=np.float64).T
        return v

    def _saturation_fallback(self, res: list, ok: np.ndarray, mask: np.ndarray, short: tuple, long: tuple,
                             bright_tab: np.ndarray) -> tuple[int, int]:
        """Fill a block's channels without weight (``ok`` False) from the shortest exposure where it
        is bright, else from the longest (``short`` / ``long``: the block's codes, value table and
        matrix), and mark those pixels in the block's ``mask``; the numbers of bright and dark pixels."""
        bad = ~ok.reshape(ok.shape[0], -1)
        pix = np.flatnonzero(bad.any(axis=0))
        none = np.broadcast_to(bad[:, pix].T, (pix.size, 3))
        z_s = short[0].reshape(-1, 3)[pix]
        z_l = long[0].reshape(-1, 3)[pix]
        if self.mode in ("brightest", "min_else_brightest"):   # the fallback sees the brightest channel
            bright = none & bright_tab[z_s.max(axis=1)][:, None]
        else:
            bright = none & bright_tab[z_s]
        dark = none & ~bright
        fs = self._values_at(z_s, short[1], short[2])
        fl = self._values_at(z_l, long[1], long[2])
        for c in range(3):
            flat = res[c].reshape(-1)
            flat[pix] = np.where(bright[:, c], fs[:, c], np.where(dark[:, c], fl[:, c], flat[pix]))
        bpix = bright.any(axis=1)
        dpix = dark.any(axis=1) & ~bpix
        mflat = mask.reshape(-1)
        mflat[pix[bpix]] = HDRResult.MASK_BRIGHT
        mflat[pix[dpix]] = HDRResult.MASK_DARK
        return int(bpix.sum()), int(dpix.sum())

    def finish(self, short: tuple, long: tuple, contiguous: bool = False, info: dict | None = None) -> HDRResult:
        """Normalise, apply the saturation policy and return the result.

        ``short`` / ``long``: ``(codes, values[, matrix])`` of the shortest and the
        longest exposure. Where the total weight of a channel is 0 the value comes from
        the shortest exposure if its value of the channel (``"brightest"``: the pixel's
        largest code) is ``>= bright_threshold``, else from the longest; ``mask`` 1
        (bright) / 2 (dark) as in merge_linear. ``contiguous=False`` returns the
        radiance as an (H, W, 3) view of the accumulator memory (no copy).
        """
        cv2 = import_cv2()
        if self.n_added == 0:
            raise InputError("no exposure was added")
        zs, zl = self._check_codes(short[0]), self._check_codes(long[0])
        vs, vl = code_table(short[1], "value"), code_table(long[1], "value")
        ms, ml = (short[2] if len(short) > 2 else None), (long[2] if len(long) > 2 else None)
        bright_tab = code_values() >= np.float32(self.bright_threshold)
        h, w = self.shape
        mask = populated_zeros((h, w), dtype=np.uint8)
        num, den, log = self.num, self.den, self.domain == "log"
        # float32 output planes: the first accumulator planes, or the first half of each float64 row
        out = num[:3] if self.dtype == np.float32 else num[:3].view(np.float32)[:, :, :w]

        def block(b0: int, b1: int) -> tuple[int, int]:
            nb = nd = 0
            d = den[:, b0:b1]
            with np.errstate(divide="ignore", invalid="ignore"):
                if len(self.sets) == 1:
                    ok = d > 0
                    res = [num[c, b0:b1] / d[0 if d.shape[0] == 1 else c] for c in range(3)]
                else:  # min_else_brightest: set 0 where it has weight, else set 1
                    use0 = d[0] > 0
                    ok = (use0 | (d[1] > 0))[None]
                    res = [np.where(use0, num[c, b0:b1] / d[0], num[3 + c, b0:b1] / d[1]) for c in range(3)]
            if not ok.all():
                nb, nd = self._saturation_fallback(res, ok, mask[b0:b1], (zs[b0:b1], vs, ms), (zl[b0:b1], vl, ml),
                                                   bright_tab)
            for c in range(3):
                r = res[c]
                if log:
                    np.minimum(r, 88.0, out=r)
                    r = r.astype(np.float32)
                    cv2.exp(r, dst=r)
                elif r.dtype != np.float32:
                    r = r.astype(np.float32)
                if not cv2.checkRange(r)[0]:
                    np.nan_to_num(r, copy=False, nan=0.0, posinf=F32_MAX, neginf=-F32_MAX)
                out[c, b0:b1] = r
            return nb, nd

        def band(b0: int, b1: int) -> tuple[int, int]:
            counts = [block(r0, min(b1, r0 + self.block_rows)) for r0 in range(b0, b1, self.block_rows)]
            return sum(c[0] for c in counts), sum(c[1] for c in counts)

        counts = self._run(band)
        self.close()
        n_bright = sum(c[0] for c in counts)
        n_dark = sum(c[1] for c in counts)
        radiance = out.transpose(1, 2, 0)
        if contiguous:
            radiance = np.ascontiguousarray(radiance)
        self.num = self.den = None  # the result owns the memory now
        out_info = {"channel_weights": self.mode, "domain": self.domain, "n_bright": n_bright, "n_dark": n_dark,
                    "engine": "table", "accumulator": self.dtype.name}
        if info:
            out_info.update(info)
        return HDRResult(radiance=radiance, mask=mask, variance=None, info=out_info)


def merge_codes(codes: Sequence[np.ndarray] | np.ndarray, times: Any, values: np.ndarray, weights: Any,
                *, image_weights: Any = None, matrices: Any = None, channel_weights: str = "mean",
                domain: str = "log", bright_threshold: float = 0.5, threads: int | None = None,
                block_rows: int | None = None, contiguous: bool = True) -> HDRResult:
    """Table merge of in-memory 8-bit exposures (N, H, W, 3) sorted or not by ``times``.

    ``values`` (N, 256, 3) per-exposure value tables, ``weights`` (256, 3) or (N, 256, 3),
    ``image_weights`` (N,), ``matrices`` (N, 3, 3) or None. Same result as
    :func:`~derender.engine.float_merge.merge_linear` on the corresponding linearisation.
    """
    t0 = time.perf_counter()
    n = len(codes)
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    if t.size != n:
        raise InputError(f"{t.size} exposure time(s) for {n} image(s)")
    if not np.all(np.isfinite(t)) or np.any(t <= 0):
        raise InputError(f"exposure times must be positive finite seconds, got {t.tolist()}")
    values = np.asarray(values, dtype=np.float32)
    if values.shape != (n, N_CODES, 3):
        raise InputError(f"values must have shape ({n}, 256, 3), got {values.shape}")
    wts = np.asarray(weights, dtype=np.float32)
    if wts.shape == (N_CODES,):
        wts = np.repeat(wts[:, None], 3, axis=1)
    if wts.shape == (N_CODES, 3):
        wts = np.broadcast_to(wts, (n, N_CODES, 3))
    if wts.shape != (n, N_CODES, 3):
        raise InputError(f"weights must have shape (256, 3) or ({n}, 256, 3), got {wts.shape}")
    iw = np.ones(n) if image_weights is None else np.asarray(image_weights, dtype=np.float64).reshape(-1)
    if iw.size != n or not np.all(np.isfinite(iw)) or np.any(iw < 0):
        raise InputError("image_weights must be N finite non-negative numbers")
    mats = [None] * n if matrices is None else [np.asarray(m, dtype=np.float64) for m in matrices]
    shape = np.asarray(codes[0]).shape[:2]
    j_short, j_long = int(np.argmin(t)), int(np.argmax(t))
    with TableMerge(shape, channel_weights=channel_weights, domain=domain, bright_threshold=bright_threshold,
                    threads=threads, block_rows=block_rows) as eng:
        for j in range(n):
            eng.add(codes[j], values[j], wts[j], image_weight=float(iw[j]), matrix=mats[j])
        res = eng.finish((codes[j_short], values[j_short], mats[j_short]), (codes[j_long], values[j_long], mats[j_long]),
                         contiguous=contiguous)
    res.info["merge_seconds"] = time.perf_counter() - t0
    return res


def merge_curves_table(stack: Stack, curves, weight: Any = "gaussian", *, domain: str = "log",
                       channel_weights: str = "mean", image_weights: Any = None, bright_threshold: float = 0.5,
                       block_rows: int | None = None, threads: int | None = None) -> HDRResult | None:
    """The table path of :func:`~derender.engine.float_merge.merge_linear` for per-channel response curves.

    Equivalent to ``merge_linear(lambda j, z: curves.log_linearise(z), stack.times,
    stack.images, weight, log_input=True, ...)``. Returns None when the stack is not
    8-bit (values not all ``code / 255``), so the caller falls back to the reference.
    """
    if stack.bit_depth == 16:
        return None
    codes = stack_codes_exact(stack.images)
    if codes is None:
        return None
    wt = weight_table(weight)
    values = curve_value_tables(curves, stack.times, domain)
    res = merge_codes(codes, stack.times, values, wt, image_weights=image_weights, channel_weights=channel_weights,
                      domain=domain, bright_threshold=bright_threshold, threads=threads, block_rows=block_rows,
                      contiguous=True)
    res.info["weight"] = weight if isinstance(weight, str) else "custom"
    return res


def code_histograms(codes: np.ndarray) -> np.ndarray:
    """Histograms (3, 256) int64 of the channels of an (H, W, 3) uint8 image."""
    cv2 = import_cv2()
    return np.stack([cv2.calcHist([codes], [c], None, [N_CODES], [0, N_CODES]).ravel().astype(np.int64)
                     for c in range(3)])
