"""Applying a de-rendering model to 8-bit images: per-pixel mean and variance of the raw colour.

* :func:`derender_image` predicts per-pixel mean and variance of the linear RAW colour
  (``derender derender``) with the model :func:`~derender.derendering.library.resolve_model`
  picks; :func:`derender_to_exr` does the same straight into EXR files, block by block (a
  24-megapixel JPEG never exists as full float images in memory). ``srgb=True`` maps the
  camera-RGB Gaussians to linear sRGB with ``A = camera_to_srgb diag(wb)`` of the model's
  metadata: ``mean' = A mean``, ``var' = (A o A) var`` (channels taken as independent).
* :func:`index_colours` finds the distinct colours of an 8-bit image: a prediction is a
  function of the colour alone, so it is made once per distinct colour and gathered.
* :func:`check_8bit_rgb` reads an image as uint8 codes (the one strict decoder) and refuses
  what the models do not describe (16-bit).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from derender.core.errors import InputError
from derender.derendering.base import finite32, model_camera_to_srgb
from derender.derendering.library import resolve_model
from derender.io.headers import DEFAULT_MAX_MEGAPIXELS

__all__ = [
    "check_8bit_rgb",
    "derender_image",
    "pack_codes",
    "ColourIndex",
    "ColourIndexBuilder",
    "index_colours",
    "derender_to_exr",
]


def check_8bit_rgb(path: str | os.PathLike, max_megapixels: float | None = DEFAULT_MAX_MEGAPIXELS) -> np.ndarray:
    """Read an 8-bit RGB image as uint8 codes (H, W, 3), upright, with the one decoder of
    every reader (:func:`derender.io.images.decode_image`: header first, strict about
    truncation); refuse 16-bit files (the models map 8-bit rendered colours)."""
    from derender.io.images import decode_image

    codes = decode_image(path, max_megapixels=max_megapixels)
    if codes.dtype != np.uint8:
        raise InputError(f"{path} is 16-bit; de-rendering models map 8-bit rendered colours")
    return codes


def derender_image(image_path: str | os.PathLike, model_path: str | os.PathLike, srgb: bool = False
                   ) -> tuple[np.ndarray, np.ndarray, str]:
    """Mean and variance (float32 (H, W, 3)) of the linear colour of every pixel, and the model used.

    Each distinct colour of the image is predicted once (:func:`index_colours`).

    Parameters
    ----------
    image_path : path-like
        An 8-bit RGB image (JPEG, PNG, TIFF) of the camera the model was fitted to.
    model_path : path-like
        A model file (:func:`derender.derendering.base.fit_model`, ``derender fit``), or a
        folder of them, from which the model of the image's EXIF camera is taken
        (:func:`derender.derendering.library.resolve_model`).
    srgb : bool
        Give linear sRGB through the model's camera matrix instead of camera RGB.

    Returns
    -------
    mean : numpy.ndarray
        (H, W, 3) float32 linear camera RGB (or linear sRGB), relative units.
    variance : numpy.ndarray
        (H, W, 3) float32 per-pixel variance of ``mean``.
    used : str
        The model file used.

    Raises
    ------
    InputError
        An unreadable or 16-bit image, no model (or none for the image's camera in a
        folder), ``srgb`` with a model without camera colour metadata.
    ModelFileError
        A corrupt or incompatible model file.

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> import derender
    >>> rng = np.random.default_rng(0)
    >>> raw = rng.uniform(0.01, 1.0, (100, 3))               # linear camera RGB
    >>> jpeg = np.round(255 * raw ** (1 / 2.2)).astype(np.uint8)   # a gamma-2.2 camera
    >>> folder = tempfile.TemporaryDirectory()
    >>> model_path = derender.fit_model("poly", jpeg, raw, degree=4).save(os.path.join(folder.name, "camera.npz"))
    >>> image_path = derender.write_png(os.path.join(folder.name, "photo.png"),
    ...                                 np.full((4, 6, 3), 128, np.uint8))
    >>> mean, variance, used = derender.derender_image(image_path, model_path)
    >>> mean.shape, mean.dtype, used
    ((4, 6, 3), dtype('float32'), 'camera.npz')
    >>> bool(np.allclose(mean, 0.5 ** 2.2, atol=0.01)), bool(np.all(variance > 0))
    (True, True)
    >>> folder.cleanup()
    """
    codes = check_8bit_rgb(image_path)
    model, used = resolve_model(model_path, image_path)
    index = index_colours(codes)
    mean_tab, var_tab = _colour_tables(model, index, srgb)
    rows = index.rows(codes)
    return np.take(mean_tab, rows, axis=0), np.take(var_tab, rows, axis=0), used


# --------------------------------------------------------------------------- colour tables
_N_PACKED = 1 << 24


def pack_codes(codes: np.ndarray) -> np.ndarray:
    """uint8 RGB codes (..., 3) -> int32 ``R << 16 | G << 8 | B`` (...,)."""
    packed = codes[..., 0].astype(np.int32)
    packed <<= 8
    packed |= codes[..., 1]
    packed <<= 8
    packed |= codes[..., 2]
    return packed


@dataclass
class ColourIndex:
    """The distinct colours of an 8-bit image and where each packed colour sits among them.

    packed : (M,) int32, sorted packed codes (:func:`pack_codes`) present in the image.
    lut : (2**24,) int32, ``lut[packed[i]] == i``; entries of absent colours are undefined.
    """

    packed: np.ndarray
    lut: np.ndarray

    @property
    def codes(self) -> np.ndarray:
        """(M, 3) int32 RGB codes of the distinct colours."""
        p = self.packed
        return np.stack([(p >> 16) & 255, (p >> 8) & 255, p & 255], axis=1).astype(np.int32)

    def rows(self, codes: np.ndarray) -> np.ndarray:
        """Row of each pixel's colour in the tables (int32, shape ``codes.shape[:-1]``)."""
        return np.take(self.lut, pack_codes(codes), mode="clip")


class ColourIndexBuilder:
    """Collects the distinct colours of several 8-bit images (a presence bitmap over the 2**24
    colours, filled in row blocks without full-size temporaries); :meth:`finish` gives the
    :class:`ColourIndex` of their union."""

    def __init__(self, block_rows: int = 64):
        self.present = np.zeros(_N_PACKED, dtype=bool)
        self.block_rows = int(block_rows)

    def add(self, codes: np.ndarray) -> None:
        if codes.dtype != np.uint8 or codes.shape[-1] != 3:
            raise InputError(f"colour indexing needs uint8 RGB codes, got {codes.dtype} {codes.shape}")
        rows = codes.reshape(-1, codes.shape[-2] if codes.ndim == 3 else 1, 3)
        for y in range(0, rows.shape[0], self.block_rows):
            self.present[pack_codes(rows[y:y + self.block_rows]).reshape(-1)] = True

    def finish(self) -> ColourIndex:
        packed = np.flatnonzero(self.present).astype(np.int32)
        lut = np.empty(_N_PACKED, dtype=np.int32)   # only the present entries are ever read
        lut[packed] = np.arange(packed.shape[0], dtype=np.int32)
        return ColourIndex(packed=packed, lut=lut)


def index_colours(codes: np.ndarray, block_rows: int = 64) -> ColourIndex:
    """Distinct colours of uint8 codes (H, W, 3) or (P, 3), scanned in row blocks.

    The cost grows with the pixels, and the tables built from the index with the distinct
    colours (a photograph has ~10^5-10^6 of them among 2.4 10^7 pixels).
    """
    builder = ColourIndexBuilder(block_rows)
    builder.add(codes)
    return builder.finish()


def _colour_tables(model, index: ColourIndex, srgb: bool, chunk: int = 1 << 18) -> tuple[np.ndarray, np.ndarray]:
    """Mean and variance (float32, finite, (M, 3)) of each distinct colour, optionally in linear sRGB."""
    m = index.packed.shape[0]
    mean = np.empty((m, 3), dtype=np.float32)
    var = np.empty((m, 3), dtype=np.float32)
    codes = index.codes
    for s in range(0, m, chunk):       # temporaries of the model bounded by the chunk
        mc, vc = model._predict_codes(codes[s:s + chunk], True, False, False)
        mean[s:s + chunk], var[s:s + chunk] = finite32(np.asarray(mc), np.asarray(vc))
    if srgb:
        mean, var = _to_linear_srgb(model, mean, var)
    return mean, var


def _to_linear_srgb(model, mean: np.ndarray, var: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera RGB Gaussians -> linear sRGB through the model's camera matrix (independent channels)."""
    a = model_camera_to_srgb(model)
    if a is None:
        raise InputError("the model has no camera colour metadata; drop --srgb to get camera RGB")
    mean = mean @ a.T.astype(np.float32)
    var = var @ (a * a).T.astype(np.float32)
    big = np.float32(np.finfo(np.float32).max / 4)
    mean = np.nan_to_num(mean, nan=0.0, posinf=big, neginf=-big).astype(np.float32)
    var = np.nan_to_num(np.clip(var, 0, big), nan=big).astype(np.float32)
    return mean, var


def derender_to_exr(image_path: str | os.PathLike, model_path: str | os.PathLike, output: str | os.PathLike,
                    variance: str | os.PathLike | None = None, srgb: bool = False,
                    compression: str = "zip", threads: int | None = None,
                    max_megapixels: float | None = DEFAULT_MAX_MEGAPIXELS) -> dict:
    """De-render an image straight into ``output`` (mean) and ``variance`` EXR files.

    The same numbers as :func:`derender_image` (each distinct colour predicted once,
    :func:`index_colours`), but the full-size mean and variance images are never formed:
    the EXR writer (:func:`derender.io.exr.write_exr_lines`) asks for 16-row blocks
    and each is gathered from the per-colour tables in its worker thread. Outputs are
    written atomically and never overwrite the input. Returns what was used and the
    timings of the stages.

    Parameters
    ----------
    image_path : path-like
        An 8-bit RGB image (JPEG, PNG, TIFF).
    model_path : path-like
        A model file, or a folder of them (as :func:`derender_image`).
    output : path-like
        The OpenEXR file of the mean.
    variance : path-like, optional
        The OpenEXR file of the variance (not written when None).
    srgb : bool
        Write linear sRGB through the model's camera matrix instead of camera RGB.
    compression : str
        The EXR compression (``"zip"``, ``"none"``, ...).
    threads : int, optional
        Threads that gather and compress the blocks (None: every CPU).
    max_megapixels : float or None
        The largest image accepted (None: no limit).

    Returns
    -------
    dict
        ``model`` (the file used), ``width``, ``height``, ``distinct_colours`` and
        ``timings`` (seconds per stage).

    Raises
    ------
    InputError
        As :func:`derender_image`; also outputs that are the same file or would overwrite
        the image.
    ModelFileError
        A corrupt or incompatible model file.

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> import derender
    >>> rng = np.random.default_rng(0)
    >>> raw = rng.uniform(0.01, 1.0, (100, 3))               # linear camera RGB
    >>> jpeg = np.round(255 * raw ** (1 / 2.2)).astype(np.uint8)   # a gamma-2.2 camera
    >>> folder = tempfile.TemporaryDirectory()
    >>> model_path = derender.fit_model("poly", jpeg, raw, degree=4).save(os.path.join(folder.name, "camera.npz"))
    >>> image_path = derender.write_png(os.path.join(folder.name, "photo.png"),
    ...                                 np.full((4, 6, 3), 128, np.uint8))
    >>> mean_path = os.path.join(folder.name, "mean.exr")
    >>> report = derender.derender_to_exr(image_path, model_path, mean_path,
    ...                                   variance=os.path.join(folder.name, "variance.exr"))
    >>> report["width"], report["height"], report["distinct_colours"]
    (6, 4, 1)
    >>> mean = derender.read_exr(mean_path)
    >>> mean.shape, bool(np.allclose(mean, 0.5 ** 2.2, atol=0.01))
    ((4, 6, 3), True)
    >>> folder.cleanup()
    """
    from derender.io.exr import write_exr_lines
    from derender.io.files import check_output

    outs = [Path(output)] + ([Path(variance)] if variance is not None else [])
    if len(outs) == 2 and outs[0].resolve() == outs[1].resolve():
        raise InputError(f"mean and variance outputs are the same file: {outs[0]}")
    for out in outs:
        check_output(out, [image_path])
    t0 = time.perf_counter()
    codes = check_8bit_rgb(image_path, max_megapixels)
    model, used = resolve_model(model_path, image_path)
    t1 = time.perf_counter()
    index = index_colours(codes)
    t2 = time.perf_counter()
    mean_tab, var_tab = _colour_tables(model, index, srgb)
    t3 = time.perf_counter()
    h, w = codes.shape[:2]
    timings = {"read_s": t1 - t0, "index_s": t2 - t1, "predict_s": t3 - t2}
    for name, out, table in (("mean", outs[0], mean_tab), ("variance", variance, var_tab)):
        if out is None:
            continue
        planes = [np.ascontiguousarray(table[:, c]) for c in (2, 1, 0)]   # B, G, R

        def lines(y0: int, y1: int, buf: np.ndarray, planes=planes) -> None:
            rows = index.rows(codes[y0:y1])
            for k in range(3):
                np.take(planes[k], rows, out=buf[:, k, :], mode="clip")  # clip: unbuffered out

        ts = time.perf_counter()
        write_exr_lines(out, w, h, lines, inputs=[image_path], compression=compression, threads=threads)
        timings[f"write_{name}_s"] = time.perf_counter() - ts
    return {"model": used, "width": w, "height": h, "distinct_colours": int(index.packed.shape[0]),
            "timings": timings}
