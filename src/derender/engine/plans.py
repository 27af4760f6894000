"""What a merge method tells the engine: how each frame's codes become radiance, and with what weight.

A method plugs into the engine (:func:`derender.engine.run.run`) by implementing
:class:`EngineMethod`: it says how it needs the frames (streamed twice, or held once)
and, once it has seen what it asked for (:class:`FrameAccess`), returns one of three
*plans*; the engine does everything else (decoding, shifts, bands, accumulation,
saturation policy, masks, outputs) and calls :meth:`EngineMethod.finish` on the result.

* :class:`TablePlan` -- per-channel 256-entry tables per frame: the value ``v_j(z)``
  each code contributes (Debevec & Malik 1997, eq. 6: ``g(z) - ln t_j`` in the log
  domain, ``f^-1(z) / t_j`` in the linear one) and its weight ``w(z)``. Run by
  :class:`~derender.engine.tables.TableMerge` (OpenCV LUTs, row blocks in threads);
  streams: the frames need not be in memory together.
* :class:`MatrixPlan` -- per-channel linearisation tables, a 3x3 matrix per frame, an
  optional inverse-variance table and integer registration shifts (paper 1, eq. 10).
  Run by :func:`~derender.engine.matrix.merge_matrix_frames` (one compiled pass per
  pixel over all held frames).
* :class:`GaussianPlan` -- a Gaussian per distinct colour (log-space mean, precision and
  censoring bound) and a scale per frame (paper 2, eq. 3). Run by
  :func:`~derender.engine.gaussian.merge_gaussian_frames` (bands of rows in threads).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Protocol

import numpy as np

__all__ = ["FrameAccess", "TablePlan", "MatrixPlan", "GaussianPlan", "SharedVariance", "EngineMethod", "MethodDefaults"]


@dataclass
class FrameAccess:
    """What a method's :meth:`~EngineMethod.plan` can read of the bracket (sorted by time).

    ``samples``: (N, P, 3) codes at the method's :meth:`~EngineMethod.sample_positions` (int32; uint8
    for a method whose positions come in clusters, ``sample_cluster`` > 1)
    (streamed methods); ``frames``: (N, H, W, 3) uint8 (held methods); ``planes``: the
    per-frame uint8 planes of :meth:`~EngineMethod.derive` (held methods, else None).
    :meth:`histograms` gives the per-frame code histograms (N, 3, 256), computed on
    first use (from the held frames, or by decoding the frames again). A method done with
    ``planes`` calls :meth:`release_planes`: the engine frees them then if it has no later
    use for their memory (``release_fn``).

    ``aligned``: the engine has registered the frames to ``reference`` (the index of the
    reference frame, by time) and may have excluded pixels: ``valid`` (N, H, W) uint8, non-zero
    where frame ``j`` takes part (None: everywhere); a method's fits should read only those
    pixels (:mod:`derender.engine.motion`: alignment, ghost removal). Streamed methods'
    ``samples`` then hold only positions valid in every frame.
    """

    times: np.ndarray
    shape: tuple[int, int]
    samples: np.ndarray | None = None
    frames: np.ndarray | None = None
    planes: np.ndarray | None = None
    histogram_fn: Callable[[], np.ndarray] | None = None
    threads: int | None = None
    info: dict = field(default_factory=dict)
    release_fn: Callable[[], None] | None = None
    reference: int | None = None
    valid: np.ndarray | None = None
    aligned: bool = False
    _hists: np.ndarray | None = None

    def release_planes(self) -> None:
        """The method no longer reads ``planes`` (they become None)."""
        self.planes = None
        if self.release_fn is not None:
            self.release_fn()

    @property
    def n(self) -> int:
        return int(self.times.shape[0])

    def histograms(self) -> np.ndarray:
        if self._hists is None:
            self._hists = self.histogram_fn()
        return self._hists


@dataclass
class TablePlan:
    """Per-channel tables of every frame (see the module docstring).

    ``values`` (N, 256, 3) float32; ``weights`` (256, 3) or (N, 256, 3); ``image_weights``
    (N,) multiplies frame j's weights; ``channel_weights`` and ``domain`` as
    :class:`~derender.engine.tables.TableMerge`. ``variance`` (a
    :class:`~derender.engine.variance.VarianceModel`): the engine also gives the result's
    variance (held frames, compiled kernel).
    """

    values: np.ndarray
    weights: np.ndarray
    image_weights: np.ndarray | None = None
    channel_weights: str = "mean"
    domain: str = "log"
    block_rows: int | None = None
    variance: Any = None

    def weight_of(self, j: int) -> np.ndarray:
        w = np.asarray(self.weights)
        return w[j] if w.ndim == 3 else w


@dataclass
class MatrixPlan:
    """Linearisation tables (N, 256, 3) float32, matrices (N, 3, 3) (frame j contributes
    ``matrices[j] @ values[j](z)``), a weight table (256, 3), an optional inverse-variance
    table (N, 256, 3) with per-frame factors (N,), and registration shifts (N, 2) (dy, dx):
    frame j is read at ``(y + dy, x + dx)``; outside the frame it does not take part.
    ``colour_weights`` (optional, (2**24,) float32, positive where read): a factor on the
    weight of every observation by its colour, indexed ``R << 16 | G << 8 | B`` (64 MB; e.g.
    the inverse relative variance of a de-rendering model, ``stabilized-probabilistic``).
    ``variance`` (a :class:`~derender.engine.variance.VarianceModel` of ``values``): the engine
    also gives the result's variance."""

    values: np.ndarray
    matrices: np.ndarray
    weights: np.ndarray
    shifts: np.ndarray
    inverse_variance: np.ndarray | None = None
    inverse_variance_k: np.ndarray | None = None
    colour_weights: np.ndarray | None = None
    variance: Any = None


@dataclass
class GaussianPlan:
    """Per distinct colour of the bracket, what one observation contributes to the product of
    Gaussians (paper 2, eq. 3), before its frame's scale: ``planes`` (9, M) float64 =
    ``[mean; precision; censoring bound]`` per channel; ``index`` maps a block of codes to
    rows of ``planes`` (:class:`derender.derendering.apply.ColourIndex`); ``log_scales`` (N,)
    is added to means and bounds of frame j; ``moments(prec, acc, bound)`` turns the
    accumulated sums of a band (3, rows, W) into (mean, variance) (rows, W, 3) float32;
    ``mask(short_codes, long_codes)`` gives the result mask of a band. ``lognormal``
    (optional) says that ``moments`` are the log-normal ones of :class:`LogNormalMoments`:
    the engine then computes sums and moments in one compiled pass
    (:func:`derender.engine.kernels.gaussian_moments_band`) instead of calling ``moments``,
    from ``table``, the planes colour-major (M, 8) ``[mean (3), p, bound (3), 0]`` (a channel's
    precision is ``p`` where its bound is ``-inf``, else 0); ``planes`` may then be None
    (:meth:`rows_planes` derives them)."""

    planes: np.ndarray | None
    index: Any
    log_scales: np.ndarray
    moments: Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
    mask: Callable[[np.ndarray, np.ndarray], np.ndarray]
    band_rows: int = 32
    lognormal: "LogNormalMoments | None" = None
    table: np.ndarray | None = None
    shared: "SharedVariance | None" = None

    def rows_planes(self) -> np.ndarray:
        """``planes`` (9, M), or derived from ``table`` when only that is given."""
        if self.planes is not None:
            return self.planes
        t = self.table
        low = np.ascontiguousarray(t[:, 4:7].T)
        p = np.where(np.isneginf(low), t[:, 3], 0.0)
        planes = [t[:, 0:3].T, p, low]
        if self.shared is not None:       # [sm; vn]: the model's log sd and the noise's log variance
            sm = t[:, 7]
            with np.errstate(divide="ignore"):
                vn = np.where(t[:, 3] > 0, np.maximum(1.0 / t[:, 3] - sm * sm, 0.0), 0.0)
            planes += [sm[None], vn[None]]
        return np.concatenate(planes)


@dataclass
class SharedVariance:
    """A :class:`GaussianPlan` whose variance keeps the model's error shared across frames
    (:mod:`derender.engine.gaussian_kernels`): ``V = sum w^2 s2n + k_model (sum w
    sm)^2 + k_pipe sum w (y - m)^2``. Its planes carry two more rows, ``[sm; vn]`` (the
    colour's model log sd and noise log variance; the table's column 7 is ``sm``); ``moments``
    then takes the extra sums ``(sq, shm, noi, hist)``."""

    k_model: float
    k_pipe: float
    k_spatial: float = 0.0
    floor_share: float = 0.01


@dataclass
class LogNormalMoments:
    """What a :class:`GaussianPlan`'s ``moments`` compute, for the compiled pass: the log-space
    product ``v = 1 / prec``, ``m = acc v``, truncated below at ``bound`` if ``censor``
    (truncated-normal moments; a bound more than 3 sigma above ``m`` dropped, a bound
    without evidence giving ``bound - 1/2`` with ``v`` 1), ``m`` clipped to ``+-max_log`` and
    ``v`` to ``[0, max_v]``, raw moments ``exp(m + v/2)`` and ``expm1(v) exp(2m + v)`` (as ``expm1(v) exp(m + v/2)^2``), mapped
    by ``matrix`` (3x3, variances by its squares) if given, float32 clipped to
    ``+-f32max/4`` (NaN means 0, NaN variances f32max/4)."""

    censor: bool
    max_log: float
    max_v: float
    matrix: np.ndarray | None = None


class EngineMethod(Protocol):
    """A merge method as the engine runs it: everything the engine reads of a method.

    ``name``; ``holds_frames``: True if :meth:`plan` needs every frame in memory (as one
    (N, H, W, 3) uint8 array), False to stream (frames decoded one at a time, twice);
    :meth:`derive` (held methods): ``fn(frame, out)`` computing one uint8 plane per frame
    in the decoding threads, or None; :meth:`sample_positions` (streamed methods): the
    pixels whose codes the calibration reads, or None; ``wants_histograms``: streamed
    methods that calibrate from code histograms get them in the first pass; ``warm_up``:
    ``"gaussian"`` to load the compiled Gaussian kernel while the frames decode, else None;
    ``output_bytes(h, w)``: the bytes of the plan's outputs, so that a held method's derived
    planes can be allocated large enough to be reused for them (None: not reused);
    ``refits_on_frames``: the plan is refitted without the pixels ghost removal rejects (the
    motion-compensated fill then runs after the refit); ``sample_cluster``: the sample positions
    come in clusters of this many (kept or left out whole); ``variance``: the method asked for
    the result's variance (the engine then holds the frames and merges with a compiled kernel);
    ``holds_outputs``: :meth:`finish` reads the merged radiance, so the outputs are held whole
    (never streamed into the files through band buffers); ``own_align``: how the method
    registers the frames itself in the plain run (``"none"``; paper 1's methods
    ``"translation"``: a :class:`~derender.engine.motion.run.MotionOptions` asking for that
    alignment and nothing else needs no motion run). :class:`MethodDefaults` gives the
    defaults of all but ``name`` and :meth:`plan`.

    A method (or its factory) with no engine form for its options raises
    :class:`~derender.engine.frames.NotStreamable`; that is the one way to ask for the float
    reference engine.
    """

    name: str
    holds_frames: bool
    wants_histograms: bool
    warm_up: str | None
    output_bytes: Callable[[int, int], int] | None
    refits_on_frames: bool
    sample_cluster: int
    variance: bool
    holds_outputs: bool
    own_align: str

    def derive(self) -> Callable[[np.ndarray, np.ndarray], Any] | None: ...

    def sample_positions(self, h: int, w: int) -> tuple[np.ndarray, np.ndarray] | None: ...

    def plan(self, access: FrameAccess) -> TablePlan | MatrixPlan | GaussianPlan: ...

    def finish(self, result: Any, access: FrameAccess) -> None: ...


class MethodDefaults:
    """The defaults of :class:`EngineMethod`'s attributes: a streamed method without derived
    planes, sample positions or histograms, no kernel warm-up, outputs not sized in advance,
    refitted after ghost removal, no registration of its own, nothing added to the result's info."""

    holds_frames: bool = False
    wants_histograms: bool = False
    warm_up: str | None = None
    output_bytes: Callable[[int, int], int] | None = None
    refits_on_frames: bool = True
    sample_cluster: int = 1
    variance: bool = False
    holds_outputs: bool = False
    own_align: str = "none"

    def derive(self) -> Callable[[np.ndarray, np.ndarray], Any] | None:
        return None

    def sample_positions(self, h: int, w: int) -> tuple[np.ndarray, np.ndarray] | None:
        return None

    def finish(self, result: Any, access: FrameAccess) -> None:
        return None
