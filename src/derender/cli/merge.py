"""What ``derender merge`` does around the library call (the command itself, with its options,
is :func:`derender.cli.hdr.merge_cmd`): the records made from its flags (the method's options,
:func:`motion_options`, :func:`flag_record`, also used by ``diagnose`` and the experiments),
the notice while numba compiles (:func:`compile_notice`), the pictures it writes beside the map
and the lines it prints when done."""

from __future__ import annotations

import contextlib
import dataclasses
import sys
from pathlib import Path
from typing import Optional

import typer

from derender.cli.app import check_model_camera
from derender.core.errors import InputError
from derender.core.types import HDRResult


@contextlib.contextmanager
def compile_notice():
    """A context in which the first compilation of a kernel prints one stderr line: a numba
    ``numba:compile`` event listener (a kernel found in numba's disk cache, ``cache=True``, is
    loaded without that event). The first merge with ``--variance --deghost`` sat silent for
    28 s here, compiling. Merges that need no kernel never import numba (0.2-0.6 s): the
    listener is registered when numba's event module is first imported, if ever
    (:class:`_AfterImport`)."""
    said = []

    def register(event) -> object:
        class CompileNotice(event.Listener):
            def on_start(self, ev) -> None:
                if not said:
                    said.append(True)
                    typer.echo("compiling kernels (first run only; cached afterwards) ...", err=True)

            def on_end(self, ev) -> None:
                pass

        listener = CompileNotice()
        event.register("numba:compile", listener)
        return listener

    registered: list = []
    hook = None
    if "numba.core.event" in sys.modules:
        registered.append(register(sys.modules["numba.core.event"]))
    else:
        hook = _AfterImport("numba.core.event", lambda module: registered.append(register(module)))
        sys.meta_path.insert(0, hook)
    try:
        yield
    finally:
        if hook is not None and hook in sys.meta_path:
            sys.meta_path.remove(hook)
        for listener in registered:
            sys.modules["numba.core.event"].unregister("numba:compile", listener)


class _AfterImport:
    """A one-shot import hook: ``callback(module)`` right after module ``name`` is first
    executed (the module is found and loaded by the usual path finder)."""

    def __init__(self, name: str, callback) -> None:
        self.name, self.callback = name, callback

    def find_spec(self, fullname, path, target=None):
        if fullname != self.name:
            return None
        import importlib.machinery

        if self in sys.meta_path:
            sys.meta_path.remove(self)
        spec = importlib.machinery.PathFinder.find_spec(fullname, path, target)
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return spec
        run, callback = spec.loader.exec_module, self.callback

        def exec_module(module) -> None:
            run(module)
            callback(module)

        spec.loader.exec_module = exec_module
        return spec


def check_method_flags(spec, *, variance: bool, model: bool, plot: bool) -> None:
    """``--variance``, ``-m`` and ``--plot`` only for a method that gives or uses them."""
    from derender.hdr.registry import METHODS

    if variance and not spec.gives_variance:
        raise InputError(f"method {spec.name!r} gives no variance (drop --variance)")
    if model and not spec.needs_model:
        users = sorted(n for n, s in METHODS.items() if s.needs_model)
        raise InputError(f"method {spec.name!r} uses no de-rendering model (drop -m; the methods that use one: "
                         f"{', '.join(users)})")
    if plot and not spec.gives_curves:
        raise InputError(f"method {spec.name!r} has no response curves to plot (drop --plot)")


def with_model(record, model: Path, image: Path, strict: bool):
    """``record`` with the ``-m`` model loaded (a file, or the library folder's model for the
    image's camera), checked against the image's camera."""
    from derender.derendering.library import resolve_model

    check_model_camera(model, image, strict)
    model_obj, used = resolve_model(model, image)
    typer.echo(f"de-rendering model: {used}", err=True)
    return dataclasses.replace(record, model=model_obj)


def method_record(spec, options: dict, *, seed: int, with_model: bool, with_variance: bool, n_images: int):
    """The method's options record of ``derender merge``, made once before any file is decoded
    (its checks, and the per-frame ones against the number of images): the ``--option``
    values and the profile's curves, ``--seed`` for a method that takes one, ``variance`` for
    the methods that compute it only when asked, and the ``-m`` model as None until it is
    loaded (a method that needs one without ``-m`` is an error here)."""
    from derender.hdr.registry import method_options

    extra = {"seed": seed} if spec.has_option("seed") else {}
    if with_variance and spec.has_option("variance"):
        extra["variance"] = True
    if with_model:
        extra["model"] = None
    record = method_options(spec.name, {**options, **extra})
    gammas = options.get("gammas")
    if gammas is not None and len(gammas) != n_images:
        raise InputError(f"--option gammas lists {len(gammas)} value(s) for {n_images} images (one per image, "
                         "in exposure order)")
    return record


def flag_record(cls, **values):
    """``cls(**values)``, a record of command-line values: its error names the field, here the
    flag (``ghost_threshold`` -> ``--ghost-threshold``)."""
    try:
        return cls(**values)
    except InputError as exc:
        name, _, rest = str(exc).partition(" ")
        raise InputError(f"--{name.replace('_', '-')} {rest}") from None


def side_outputs(result: HDRResult, images: list, inputs: list, *, preview, mask, ghost_mask, plot) -> None:
    """The merge's optional pictures (each None or a transaction's temporary path): the tone-mapped
    preview, the saturation mask, the ghost mask and the response curves' plot."""
    import numpy as np

    from derender.io.preview import write_png, write_preview

    if preview is not None:
        write_preview(preview, result.radiance, inputs=inputs)
    if mask is not None:
        m = np.zeros(result.mask.shape, np.uint8)
        m[result.mask == HDRResult.MASK_BRIGHT] = 128
        m[result.mask == HDRResult.MASK_DARK] = 255
        write_png(mask, np.repeat(m[:, :, None], 3, axis=2), inputs=inputs)
    if ghost_mask is not None:
        write_png(ghost_mask, _ghost_png(result.ghosts, len(images)), inputs=inputs)
    if plot is not None:
        from derender.response.curves import plot_response

        plot_response(result.info["curves"], plot, inputs=inputs)


def merge_summary(result: HDRResult, images: list, method: str, output: Path, seconds: float,
                   with_variance: bool) -> None:
    """The lines ``derender merge`` prints when done, from the merge's one summary record
    (:class:`derender.hdr.summary.MergeSummary`, the same the output and the report hold):
    sizes, time, clipped and taken pixels, the variance's sources, the reference frame,
    alignment and ghosts."""
    rec = result.info["summary"]
    typer.echo(f"{method}: {len(images)} images {rec.width}x{rec.height} -> {output} ({seconds:.2f} s; "
               f"{rec.counts_text()})")
    sources = result.info.get("variance_sources")
    if with_variance and sources:
        typer.echo("variance by source (median share of a pixel's): "
                   + ", ".join(f"{k} {100 * v:.0f} %" for k, v in sources.items()))
        spread = result.info.get("variance_curve_sd")
        if spread is not None:
            typer.echo(f"curve spread over resampled calibration samples {spread:.3f} (ln): shared term "
                       f"{result.info['variance_shared']:.3f}, noise x {result.info['variance_inflate']:.3g}")
    noise = result.info.get("noise") if result.info.get("engine_path") == "raw" else None
    if noise:
        how = {"pairs": "estimated from the frame pairs", "green-pairs": "estimated from one frame's green pairs "
               "(an upper bound where the scene has texture)", "NoiseProfile": "from the DNG NoiseProfile",
               "given": "as given"}.get(noise["source"], noise["source"])
        typer.echo(f"sensor noise: gain {noise['gain_dn_per_electron']:.4g} DN/electron, read noise "
                   f"{noise['read_noise_dn']:.3g} DN ({how})")
    if result.info.get("note"):
        typer.echo(f"note: {result.info['note']}")
    motion_line = rec.motion_text()
    if motion_line:
        typer.echo(motion_line)


def motion_options(reference: Optional[str], align: Optional[str], deghost: bool, threshold: Optional[float],
                   ghost_mask: Optional[Path], n_images: int, seed: int = 0):
    """The :class:`~derender.engine.motion.run.MotionOptions` of ``derender merge``, made once
    (``--reference`` counts from 1; every value checked by the record, its errors naming the
    flags)."""
    from derender.engine.motion.run import MotionOptions

    ref = None
    if reference is not None:
        text = reference.strip().lower()
        if text != "auto":
            try:
                k = int(text)
            except ValueError:
                raise InputError(f"--reference takes N (from 1) or 'auto', got {reference!r}") from None
            if not 1 <= k <= n_images:
                raise InputError(f"--reference {k} is out of range: {n_images} images given (1..{n_images})")
            ref = k - 1
    if threshold is not None and not deghost:
        raise InputError("--ghost-threshold sets the test of --deghost; add --deghost")
    if ghost_mask is not None and not deghost and align in (None, "none"):
        raise InputError("--ghost-mask shows where --deghost or --align left frames out; add one of them")
    return flag_record(MotionOptions, reference=ref, align=align, deghost=deghost, ghost_threshold=threshold,
                       seed=seed)


def _ghost_png(ghosts, n_images: int):
    """8-bit RGB picture of :attr:`HDRResult.ghosts`: frames left out (or replaced by their
    motion-compensated view) per pixel, 255 = all but the reference."""
    import numpy as np

    g = np.zeros((1, 1), np.uint8) if ghosts is None else np.asarray(ghosts)
    v = np.clip(np.rint(g.astype(np.float64) * (255.0 / max(n_images - 1, 1))), 0, 255).astype(np.uint8)
    return np.repeat(v[:, :, None], 3, axis=2)


def merge_report(path, result, method: str, absolute: bool, view: str | None, inputs) -> None:
    """``--report``: the page of the merged map, its summary table the merge's one record."""
    from derender.applications.report import write_report
    from derender.io.rgbe import SRGB_PRIMARIES
    from derender.photometry.projection import parse_view

    curves = result.info.get("curves")
    write_report(path, result.radiance, variance=result.variance, mask=result.mask, ghost_mask=result.ghosts,
                 absolute=absolute, primaries=SRGB_PRIMARIES, summary=result.info["summary"].rows(),
                 curves=getattr(curves, "log_inverse", None), view=parse_view(view) if view else None,
                 title=f"derender merge --method {method}", inputs=inputs)
