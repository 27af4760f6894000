"""Does a bracket have one rendering? A test on the frames' own codes, without truth or a fitted curve.

Debevec & Malik (1997) and Robertson et al. (2003) assume one fixed response curve ``f_c`` per
channel and exposures proportional to the stated times: frame ``j`` renders ``z = f_c(E t_j)``.
Paper 1 (Sec. 3) starts from cameras that break this: a phone may change gain, white balance or
tone curve between frames. Whether a bracket breaks it can be read from its codes alone.

Under one increasing curve, the *intensity mapping* of a pair of frames ``a -> b``
(``IMF_ab(z)``: the code in frame ``b`` of the pixels that have code ``z`` in frame ``a``) is
``f(r_ab f^-1(z))`` with ``r_ab = t_b / t_a``: it depends on the ratio only, and grows with it.
So for two pairs with ``r_p >= r_q``,

    IMF_p(z) >= IMF_q(z)        for every code z and channel,

whatever ``f`` is. A pair ``q`` whose frames, at the same code, end further apart than a pair
``p`` of larger ratio is a contradiction no single curve can fit: one of the two pairs was not
rendered as its times say. The *violation* is ``IMF_q(z) - IMF_p(z)`` in codes
(:func:`one_rendering`).

Measured on smooth, well-exposed blocks (the median codes of ``B x B`` tiles,
:data:`~derender.evaluation.consistency.BLOCK`, whose codes span at most
:data:`~derender.evaluation.consistency.FIDELITY_FLAT` codes in both frames: edges and
misregistration stay out), at the codes of :data:`IMF_CODES` (away from a curve's toe, where
one code stands for a range of exposures) with at least :data:`IMF_MIN_BLOCKS` blocks within
:data:`IMF_HALF_WIDTH` codes, for pairs up to :data:`MAX_RATIO` apart. A bracket has no one
rendering when more than :data:`VIOLATION_FRACTION` of the tests violate by more than
:data:`VIOLATION_CODES`.

Measured (``tests/evaluation/test_rendering_change.py``):

* simulator, exact truth (outdoor, 768x512, 9 frames 1 stop apart, 8 px blocks, seeds 0-2): the
  ``fixed`` pipeline 0-2 of 2114-2647 tests violate (largest 7-10 codes), the ``auto`` pipeline
  379-488 of 1923-2654 (largest 49-86 codes);
* real, no truth (``derender experiment consistency``): the iPhone 6 bracket (handheld, registered
  by translation) 131 of 2044 tests, largest 45 codes (red, code 135: frames 2 -> 3, EXIF ratio
  2.05, give 143; frames 7 -> 8, ratio 2.00, give 188); Debevec's Memorial (film) 0 of 37 (largest
  0.5 codes), Frobisher 0 of 2 (0.5 codes).

:func:`frame_predictions` asks the same of a method: what each frame's codes say the map is in a
region, through the method's own forward model (docs/uncertainty.md, the iPhone's sky).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["IMF_CODES", "IMF_HALF_WIDTH", "IMF_MIN_BLOCKS", "IMF_LOW", "IMF_HIGH", "VIOLATION_CODES", "VIOLATION_FRACTION",
           "RATIO_TOLERANCE", "MAX_RATIO", "OneRendering", "frame_predictions", "DECIMATE_ABOVE", "bracket_one_rendering", "block_codes", "intensity_mappings", "one_rendering"]

#: The codes at which the intensity mappings are read.
IMF_CODES = np.arange(40, 216, 5)

#: Blocks of frame ``a`` within this many codes of ``z`` give ``IMF(z)``.
IMF_HALF_WIDTH = 4

#: ``IMF(z)`` needs this many blocks (else it is not read).
IMF_MIN_BLOCKS = 20

#: Blocks whose median code in either frame of a pair is below this ...
IMF_LOW = 8

#: ... or above this are left out (clipped or near black).
IMF_HIGH = 247

#: A test violates when the mappings cross by more than this many codes (a median of 20 blocks
#: carries a few codes of noise and quantisation: simulated fixed pipelines reach 7-10 codes in
#: 0-2 of their ~2100-2650 tests, the module docstring).
VIOLATION_CODES = 8.0

#: A bracket has no one rendering when more than this fraction of its tests violate.
VIOLATION_FRACTION = 0.02

#: Only pairs whose exposure ratio is at most this are compared: across many stops a code in
#: a curve's toe (a film's base fog, a sensor's black level) stands for a wide range of exposures,
#: and its mapping depends on what the scene holds at that code.
MAX_RATIO = 8.5

#: Two pairs whose ratios differ by less than this factor are tested both ways (equal ratios
#: must give equal mappings).
RATIO_TOLERANCE = 1.0


def block_codes(frames: np.ndarray, block: int | None = None, valid: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """Per frame the per-channel median codes (N, h, w, 3) float32 of ``block x block`` tiles of
    ``frames`` (N, H, W, 3) uint8 and whether each tile is smooth (N, h, w) bool: every channel's
    codes within :data:`~derender.evaluation.consistency.FIDELITY_FLAT` (interdecile range) and,
    with ``valid`` (N, H, W) bool, every pixel valid."""
    from derender.evaluation.consistency import BLOCK, FIDELITY_FLAT

    b = BLOCK if block is None else int(block)
    arr = np.asarray(frames)
    n, hh, ww = arr.shape[:3]
    h, w = hh // b, ww // b
    med = np.empty((n, h, w, 3), np.float32)
    smooth = np.empty((n, h, w), bool)
    for j in range(n):
        t = arr[j, :h * b, :w * b].reshape(h, b, w, b, 3).swapaxes(1, 2).reshape(h, w, b * b, 3)
        q = np.quantile(t, [0.1, 0.5, 0.9], axis=2)
        med[j] = q[1]
        smooth[j] = np.all(q[2] - q[0] <= FIDELITY_FLAT, axis=-1)
        if valid is not None:
            v = np.asarray(valid[j])[:h * b, :w * b].reshape(h, b, w, b).swapaxes(1, 2).reshape(h, w, -1)
            smooth[j] &= v.all(axis=-1)
    return med, smooth


def intensity_mappings(med: np.ndarray, smooth: np.ndarray, region: np.ndarray | None = None
                       ) -> dict[tuple[int, int], np.ndarray]:
    """``IMF_ab`` (3, len(IMF_CODES)) float64 (NaN where not read) for every pair ``a < b`` of
    frames from :func:`block_codes` (``region`` (h, w) bool: the blocks to use, e.g. no screen)."""
    n = med.shape[0]
    out = {}
    for a in range(n):
        for b in range(a + 1, n):
            ok = smooth[a] & smooth[b]
            if region is not None:
                ok &= region
            za, zb = med[a][ok], med[b][ok]
            keep = np.all((za > IMF_LOW) & (za < IMF_HIGH) & (zb > IMF_LOW) & (zb < IMF_HIGH), axis=-1)
            za, zb = za[keep], zb[keep]
            imf = np.full((3, IMF_CODES.size), np.nan)
            for c in range(3):
                for i, z in enumerate(IMF_CODES):
                    s = np.abs(za[:, c] - z) <= IMF_HALF_WIDTH
                    if np.count_nonzero(s) >= IMF_MIN_BLOCKS:
                        imf[c, i] = float(np.median(zb[s, c]))
            out[(a, b)] = imf
    return out


@dataclass
class OneRendering:
    """The largest violation (codes) of ``IMF_p(z) >= IMF_q(z)`` for ``r_p >= r_q`` (module
    docstring), where it is (``pair_p``, ``pair_q`` as (a, b) indices of the frames as given,
    from 0; ``code``, ``channel`` 0-2, the two mappings ``imf_p``, ``imf_q`` and ratios ``ratio_p``,
    ``ratio_q``), how many (pair, pair, code, channel) tests were made and how many violate by
    more than :data:`VIOLATION_CODES`. ``one_rendering``: at most :data:`VIOLATION_FRACTION` of
    the tests violate (true when nothing could be tested: nothing contradicts one curve)."""

    violation: float
    pair_p: tuple[int, int] | None = None
    pair_q: tuple[int, int] | None = None
    ratio_p: float = float("nan")
    ratio_q: float = float("nan")
    code: int = -1
    channel: int = -1
    imf_p: float = float("nan")
    imf_q: float = float("nan")
    tests: int = 0
    violations: int = 0
    mappings: dict = field(default_factory=dict, repr=False)

    @property
    def fraction(self) -> float:
        """The fraction of the tests that violate by more than :data:`VIOLATION_CODES` (0 without tests)."""
        return self.violations / self.tests if self.tests else 0.0

    @property
    def one_rendering(self) -> bool:
        """True when at most :data:`VIOLATION_FRACTION` of the tests violate."""
        return self.fraction <= VIOLATION_FRACTION

    def row(self) -> dict:
        """JSON-friendly (frames counted from 1, as the CLI does)."""
        f = (lambda p: None if p is None else [p[0] + 1, p[1] + 1])   # noqa: E731
        return {"violation": self.violation, "pair_p": f(self.pair_p), "pair_q": f(self.pair_q),
                "ratio_p": self.ratio_p, "ratio_q": self.ratio_q, "code": self.code, "channel": "RGB"[self.channel]
                if self.channel >= 0 else None, "imf_p": self.imf_p, "imf_q": self.imf_q, "tests": self.tests,
                "violations": self.violations, "fraction": self.fraction, "one_rendering": self.one_rendering}


def one_rendering(frames: np.ndarray, times, *, valid: np.ndarray | None = None, region: np.ndarray | None = None,
                  block: int | None = None) -> OneRendering:
    """The one-rendering test (module docstring) of registered ``frames`` (N, H, W, 3) uint8 with
    exposure ``times`` (N,) in any order (``valid`` (N, H, W) bool: pixels a frame covers after
    registration; ``region`` (h, w) bool over the blocks: where to look, e.g. leaving a flickering
    screen out)."""
    t = np.asarray(times, dtype=np.float64)
    order = np.argsort(t, kind="stable")
    fr = np.asarray(frames)[order]
    va = None if valid is None else np.asarray(valid)[order]
    t = t[order]
    med, smooth = block_codes(fr, block, va)
    maps = intensity_mappings(med, smooth, region)
    pairs = [p for p in maps if t[p[1]] / t[p[0]] <= MAX_RATIO]
    best = OneRendering(violation=-np.inf, mappings=maps)
    tests = bad = 0
    for p in pairs:
        rp = t[p[1]] / t[p[0]]
        for q in pairs:
            if q == p:
                continue
            rq = t[q[1]] / t[q[0]]
            if rp < rq * RATIO_TOLERANCE:
                continue
            d = maps[q] - maps[p]                 # > 0: the smaller ratio moved the codes further
            ok = np.isfinite(d)
            tests += int(ok.sum())
            bad += int(np.count_nonzero(d[ok] > VIOLATION_CODES))
            if ok.any():
                c, i = np.unravel_index(np.nanargmax(np.where(ok, d, -np.inf)), d.shape)
                if d[c, i] > best.violation:
                    best = OneRendering(violation=float(d[c, i]), pair_p=(int(order[p[0]]), int(order[p[1]])),
                                        pair_q=(int(order[q[0]]), int(order[q[1]])), ratio_p=float(rp),
                                        ratio_q=float(rq), code=int(IMF_CODES[i]), channel=int(c),
                                        imf_p=float(maps[p][c, i]), imf_q=float(maps[q][c, i]), mappings=maps)
    best.tests, best.violations = tests, bad
    if not np.isfinite(best.violation):
        best.violation = float("nan")
    return best


def frame_predictions(plan, frames: np.ndarray, region: np.ndarray, *, low: int = IMF_LOW,
                      high: int = IMF_HIGH) -> np.ndarray:
    """What each frame's own codes say the map is in ``region`` (H, W) bool, through a method's
    forward model: per frame (time order, as the plan) and channel the median over the region's
    pixels the frame sees unclipped (every channel in (``low``, ``high``)) of ``ln`` of the
    plan's value of its codes (table plans: the frame's table, ``g(z) - ln t_j`` or its linear
    form; matrix plans: ``ln(M_j L_j(z))``), (N, 3) float64, NaN where the frame sees too little
    of the region (fewer than a tenth of its pixels). ``frames`` (N, H, W, 3) uint8 on the
    plan's grid. Where the model holds every frame says the same; the spread over frames is
    the model's failure there (module docstring of :mod:`derender.evaluation.roundtrip`)."""
    from derender.engine.plans import MatrixPlan, TablePlan

    n = frames.shape[0]
    out = np.full((n, 3), np.nan)
    sel = np.asarray(region, bool)
    total = max(int(sel.sum()), 1)
    ch = np.arange(3)
    for j in range(n):
        z = np.asarray(frames[j])[sel].astype(np.intp)
        ok = np.all((z > low) & (z < high), axis=-1)
        if ok.sum() < 0.1 * total:
            continue
        vals = np.asarray(plan.values[j], dtype=np.float64)[z[ok], ch]
        if isinstance(plan, TablePlan):
            logv = vals if plan.domain == "log" else np.log(np.maximum(vals, 1e-300))
        elif isinstance(plan, MatrixPlan):
            mixed = vals @ np.asarray(plan.matrices[j], dtype=np.float64).T
            logv = np.log(np.maximum(mixed, 1e-300))
        else:
            raise TypeError(f"no forward model for a {type(plan).__name__} (table and matrix plans only)")
        out[j] = np.median(logv, axis=0)
    return out


#: :func:`bracket_one_rendering` reads frames larger than this (pixels) at every second pixel
#: (and halves the block): the test's blocks keep their size in the scene, the registration's
#: float copies a quarter of the memory (the iPhone's 8 MP frames: 0.19 GB instead of 0.75).
DECIMATE_ABOVE = 4_000_000


def bracket_one_rendering(name: str, root=None, spec: dict | None = None) -> OneRendering:
    """:func:`one_rendering` of the real bracket ``name`` of
    :data:`~derender.evaluation.consistency.STILL_BRACKETS` (``spec``: another folder/times
    spec in that form): its files' codes and times, registered by integer translation to its
    reference when its alignment is not ``none`` (a flow's sub-pixel warp would resample the
    codes), pixels a frame does not cover left out."""
    from derender.engine.motion.align import align_images
    from derender.evaluation.consistency import BLOCK, bracket_inputs
    from derender.io.exif import file_times
    from derender.io.images import read_codes

    paths, kw = bracket_inputs(name, root, spec)
    times = file_times(paths, None, kw.get("times_file"), kw.get("times_file_inverse", False))
    first = read_codes(paths[0])
    step = 2 if first.shape[0] * first.shape[1] > DECIMATE_ABOVE else 1
    frames = np.stack([first[::step, ::step]] + [read_codes(p)[::step, ::step] for p in paths[1:]])
    valid = None
    if kw["motion"].align != "none":
        al = align_images(frames, "translation", reference=kw["motion"].reference)
        frames = np.clip(np.rint(al.images), 0, 255).astype(np.uint8)
        valid = al.valid
    return one_rendering(frames, times, valid=valid, block=BLOCK // step)
