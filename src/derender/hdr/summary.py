"""One summary record of a merge, made once and shown the same way everywhere.

:func:`derender.hdr.files.merge_files` makes a :class:`MergeSummary` from its result
(``info["summary"]``); ``derender merge`` prints it (:meth:`MergeSummary.lines`), the EXR or
.hdr output stores it (the ``derender:summary`` attribute, the ``DERENDER_SUMMARY=`` header
line: :meth:`MergeSummary.to_json`), and the HTML report shows it (:meth:`MergeSummary.rows`),
read back from the output by ``derender report`` (:meth:`MergeSummary.from_json`). Before
this record the report and the CLI disagreed (issue 36): the report numbered the reference
frame from 0 in time order, the CLI from 1 as given; the report's "over-exposed" count was
another quantity than the CLI's "clipped" count.

Conventions, the same in every view:

* frames are numbered **from 1, in the order the images were given**, and always shown with
  their file name (``image 2 (IMG_0002.JPG)``);
* shifts are ``(dy, dx)`` pixels per image, in that order, the reference's ``(0, 0)``;
* ``clipped_shortest``: pixels with a channel at code 255 in the shortest exposure;
  ``from_shortest`` / ``from_longest``: pixels no frame could merge under the method's
  weights, taken from the shortest (over-exposed everywhere) or the longest exposure (the
  ``--mask`` codes 128 and 255).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Sequence

import numpy as np

from derender.core.types import HDRResult

__all__ = ["FrameRecord", "MergeSummary", "merge_summary_record", "attach_summary", "SUMMARY_ATTRIBUTE", "SUMMARY_HEADER"]

#: The EXR header attribute holding the record (JSON text).
SUMMARY_ATTRIBUTE = "derender:summary"

#: The Radiance header line holding the record (``DERENDER_SUMMARY= {...}``).
SUMMARY_HEADER = "DERENDER_SUMMARY"


@dataclass(frozen=True)
class FrameRecord:
    """One input image: its place among the images as given (from 1), name and exposure."""

    image: int
    name: str
    time_s: float
    f_number: float | None = None
    iso: float | None = None

    def label(self) -> str:
        return f"image {self.image} ({self.name})"


@dataclass(frozen=True)
class MergeSummary:
    """What a merge did, in the conventions of the module docstring."""

    method: str
    width: int
    height: int
    frames: tuple[FrameRecord, ...]
    reference: int | None = None                 # image number as given, from 1
    align: str | None = None
    shifts: tuple[tuple[int, int], ...] | None = None   # per image as given: (dy, dx) px
    clipped_shortest: int | None = None
    from_shortest: int = 0
    from_longest: int = 0
    ghost_threshold: float | None = None
    ghost_rejected: float | None = None          # share of the other frames' pixels left out
    photometric_factor: float | None = None
    photometric_source: str | None = None
    extra: dict = field(default_factory=dict)

    # ---------------------------------------------------------------- views
    def frame(self, image: int) -> FrameRecord:
        return self.frames[image - 1]

    def reference_label(self) -> str | None:
        return None if self.reference is None else self.frame(self.reference).label()

    def largest_shift(self) -> int | None:
        if not self.shifts:
            return None
        return max(max(abs(a), abs(b)) for a, b in self.shifts)

    def shifts_text(self) -> str | None:
        """``image 1 (a.jpg) 0,0; image 2 (b.jpg) 4,34; ...`` (dy,dx px), or None."""
        if self.shifts is None:
            return None
        return "; ".join(f"{f.label()} {dy},{dx}" for f, (dy, dx) in zip(self.frames, self.shifts))

    def counts_text(self) -> str:
        clipped = (f"{self.clipped_shortest} px clipped even in the shortest exposure; "
                   if self.clipped_shortest is not None else "")
        return (f"{clipped}{self.from_shortest} px taken from the shortest exposure, {self.from_longest} px from "
                "the longest (mask)")

    def motion_text(self) -> str:
        """The reference, alignment and ghost removal in one line ('' when none was asked for)."""
        parts = []
        if self.reference is not None:
            parts.append(f"reference frame {self.reference} ({self.frame(self.reference).name})")
        if self.align == "translation" and self.shifts is not None:
            parts.append(f"aligned by translation (largest shift {self.largest_shift()} px)")
        elif self.align == "homography":
            parts.append("aligned by homography")
        if self.ghost_rejected is not None:
            parts.append(f"ghost removal left out {100 * self.ghost_rejected:.1f} % of the other frames' pixels")
        return "; ".join(parts)

    def rows(self) -> dict[str, str]:
        """The report's summary table: label -> text (the same numbers as :meth:`motion_text`
        and :meth:`counts_text`, which the CLI prints)."""
        out = {"method": self.method, "size": f"{self.width}x{self.height}"}
        frames = []
        for f in sorted(self.frames, key=lambda f: f.time_s):
            text = f"{f.label()}: {_seconds(f.time_s)}"
            if f.f_number:
                text += f", f/{f.f_number:g}"
            if f.iso:
                text += f", ISO {f.iso:g}"
            frames.append(text)
        out["frames (by exposure time)"] = "; ".join(frames)
        if self.reference is not None:
            out["reference frame"] = self.reference_label()
        if self.align is not None:
            out["alignment"] = self.align
        if self.shifts is not None:
            out["alignment shifts (dy,dx px)"] = self.shifts_text() + f" (largest {self.largest_shift()} px)"
        if self.ghost_rejected is not None:
            out["ghost removal"] = (f"threshold {self.ghost_threshold:g}, " if self.ghost_threshold is not None
                                    else "") + (f"left out {100 * self.ghost_rejected:.1f} % of the other frames' "
                                                "pixels (overlay: ghosts)")
        if self.clipped_shortest is not None:
            out["clipped even in the shortest exposure"] = f"{self.clipped_shortest} px"
        out["taken from the shortest exposure (mask)"] = f"{self.from_shortest} px"
        out["taken from the longest exposure (mask)"] = f"{self.from_longest} px"
        if self.photometric_factor is not None:
            out["photometric factor"] = f"{self.photometric_factor:.6g}" + (
                f" ({self.photometric_source})" if self.photometric_source else "")
        return out

    # ---------------------------------------------------------------- storage
    def to_json(self) -> str:
        """One line of JSON (an EXR attribute, a Radiance header line)."""
        return json.dumps(asdict(self), separators=(",", ":"), default=_plain)

    @classmethod
    def from_json(cls, text: str) -> "MergeSummary | None":
        """The record stored by :meth:`to_json`; None for blank or unreadable text."""
        text = (text or "").strip()
        if not text:
            return None
        try:
            d = json.loads(text)
            frames = tuple(FrameRecord(**f) for f in d.pop("frames"))
            shifts = d.pop("shifts")
            return cls(frames=frames, shifts=None if shifts is None else tuple(tuple(s) for s in shifts), **d)
        except (ValueError, TypeError, KeyError):
            return None

    def with_photometry(self, factor: float | None, source: str | None) -> "MergeSummary":
        return replace(self, photometric_factor=None if factor is None else float(factor),
                       photometric_source=source)


def _seconds(t: float) -> str:
    return f"1/{1 / t:.4g} s" if 0 < t < 1 else f"{t:.4g} s"


def _plain(v: Any) -> Any:
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    raise TypeError(type(v).__name__)


def attach_summary(res: HDRResult, paths: Sequence, times: Sequence[float], method: str,
                   outputs: Sequence = ()) -> MergeSummary:
    """Make the record of ``res`` (:func:`merge_summary_record`, EXIF f-numbers and ISO read
    again: headers only), keep it as ``res.info["summary"]`` and write it into the EXR
    ``outputs`` already written (their reserved ``derender:summary`` attribute, filled in
    place: :func:`derender.io.exr.fill_exr_attribute`)."""
    from derender.io.exif import read_exif
    from derender.io.exr import fill_exr_attribute

    shape = res.mask.shape[:2] if res.mask is not None else (res.radiance.shape[:2] if res.radiance is not None
                                                             else (0, 0))
    record = merge_summary_record(res.info, res.mask, shape, method, paths, times, [read_exif(p) for p in paths])
    res.info["summary"] = record
    for out in outputs:
        if out is not None:
            fill_exr_attribute(out, SUMMARY_ATTRIBUTE, record.to_json())
    return record


def merge_summary_record(info: dict, mask: np.ndarray | None, shape: tuple[int, int], method: str,
                         paths: Sequence, times: Sequence[float], exifs: Sequence[dict] | None = None) -> MergeSummary:
    """The :class:`MergeSummary` of a merge result: ``info`` its ``HDRResult.info``, ``mask``
    its saturation mask (1 taken from the shortest exposure, 2 from the longest), ``shape``
    (H, W), ``paths`` and ``times`` the images and their exposure times **as given**.

    The engine's motion path records the reference as ``info["reference_input"]`` (an index
    among the images as given) and its shifts in exposure order (``info["alignment"]``); the
    stabilised merges' own registration records both in exposure order (``info["reference"]``,
    ``info["shifts"]``). Both are mapped here to the images as given."""
    from pathlib import Path

    t = np.asarray(times, dtype=np.float64)
    order = np.argsort(t, kind="stable")          # frame k by time is image order[k] as given
    exifs = list(exifs) if exifs is not None else [{}] * len(paths)
    frames = tuple(FrameRecord(i + 1, Path(p).name, float(t[i]), exifs[i].get("FNumber"), exifs[i].get("ISO"))
                   for i, p in enumerate(paths))
    ref = info.get("reference_input")
    if ref is None and isinstance(info.get("reference"), (int, np.integer)):
        ref = int(order[int(info["reference"])])
    al = info.get("alignment") or {}
    align = al.get("align") if al.get("align") not in (None, "none") else None
    shifts_time = al.get("shifts")
    if not al and info.get("align") not in (None, "none"):     # the stabilised merges' own registration
        align = str(info["align"])
        shifts_time = info.get("shifts")
    shifts = None
    if shifts_time is not None and len(shifts_time) == len(paths):
        by_input = [(0, 0)] * len(paths)
        for k, s in enumerate(shifts_time):
            by_input[int(order[k])] = (int(s[0]), int(s[1]))
        shifts = tuple(by_input)
    dg = info.get("deghost") or {}
    m = np.asarray(mask) if mask is not None else None
    return MergeSummary(
        method=str(info.get("method", method)), width=int(shape[1]), height=int(shape[0]), frames=frames,
        reference=None if ref is None else int(ref) + 1, align=align, shifts=shifts,
        clipped_shortest=None if info.get("n_clipped") is None else int(info["n_clipped"]),
        from_shortest=int(np.count_nonzero(m == HDRResult.MASK_BRIGHT)) if m is not None else int(info.get("n_bright", 0)),
        from_longest=int(np.count_nonzero(m == HDRResult.MASK_DARK)) if m is not None else int(info.get("n_dark", 0)),
        ghost_threshold=None if not dg else (None if dg.get("threshold") is None else float(dg["threshold"])),
        ghost_rejected=None if not dg else float(dg.get("rejected", 0.0)),
        photometric_factor=info.get("photometric_factor"), photometric_source=info.get("photometric_source"))
