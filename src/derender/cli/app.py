"""The typer application and the helpers its commands share (options, progress, cameras)."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from derender.core.errors import InputError


def click_exception_types() -> tuple[tuple[type, ...], tuple[type, ...], tuple[type, ...]]:
    """(ClickException, Abort, Exit) classes of the click typer uses (vendored since typer 0.2x)."""
    errs, aborts, exits = [], [typer.Abort], [typer.Exit]
    for modname in ("typer._click.exceptions", "click.exceptions"):
        try:
            mod = __import__(modname, fromlist=["ClickException"])
        except ImportError:
            continue
        errs.append(mod.ClickException)
        if hasattr(mod, "Abort"):
            aborts.append(mod.Abort)
        if hasattr(mod, "Exit"):
            exits.append(mod.Exit)
    return tuple(errs), tuple(aborts), tuple(exits)

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Recover linear scene radiance, with uncertainty, from rendered camera images.")


def command():
    """The click command of :data:`app`, with flags shown as flags in ``--help``.

    Typer 0.29 with click 8.5 prints every boolean flag with a ``<bool>`` metavar
    (``--times-inverse <bool>``) although it takes no value; an empty metavar on
    each flag (including ``--help``) restores ``--times-inverse``."""
    import typer.main

    cmd = typer.main.get_command(app)
    stack = [cmd]
    while stack:
        c = stack.pop()
        for p in getattr(c, "params", ()):
            if getattr(p, "is_flag", False):
                p.metavar = ""
            if getattr(p, "param_type_name", "") == "argument" and hasattr(p, "_usage_display_name"):
                p._usage_display_name = _usage_name(p)
        c.get_help_option = _flag_help(c.get_help_option)
        stack.extend(getattr(c, "commands", {}).values())
    return cmd


def _usage_name(param):
    def name() -> str:
        text = (param.metavar or param.name or "").upper()
        if not param.required:
            text = f"[{text}]"
        return text + ("..." if param.nargs != 1 else "")

    return name


def _flag_help(get_help_option):
    def get(ctx):
        opt = get_help_option(ctx)
        if opt is not None:
            opt.metavar = ""
        return opt

    return get


_FAST_EXIT = False


def fast_exit_gc() -> None:
    """At interpreter exit, move every live object to the collector's permanent generation
    (``gc.freeze``) so that shutdown does not walk them: with numba loaded (stabilised
    merges) that walk cost 0.3-0.4 s per run here, against 0.03-0.05 s frozen. Registered
    with atexit, so it runs only once the command is over (outputs written and closed) and
    in-process callers keep a normal collector; other atexit handlers and module teardown
    still run."""
    global _FAST_EXIT
    if not _FAST_EXIT:
        import atexit
        import gc

        atexit.register(gc.freeze)
        _FAST_EXIT = True


def console():
    from rich.console import Console

    return Console(stderr=True)


def progress():
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                    TimeElapsedColumn(), console=console(), transient=False)


def parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"--size must look like 480x320, got {text!r}") from None
    if w < 32 or h < 32 or w * h > 400_000_000:
        raise InputError(f"--size {text} out of range (32x32 to 400 MP)")
    return w, h


def check_choice(option: str, value: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        from derender.core.options import did_you_mean

        raise InputError(f"{option} must be one of {', '.join(choices)}, got {value!r}{did_you_mean(value, choices)}")


def load_camera_cli(camera: str, camera_file: Optional[Path]):
    from derender.camera.spectral import load_camera, load_camera_file

    if camera_file is not None:
        return load_camera_file(camera_file)
    return load_camera(camera)   # one search order for the whole tool (camera_search_order)


def check_times_options(times: Optional[str], times_file: Optional[Path], times_inverse: bool) -> None:
    """The time options that only make sense together, checked together."""
    if times is not None and times_file is not None:
        raise InputError("give either --times or --times-file, not both")
    if times_inverse and times_file is None:
        raise InputError("--times-inverse applies to a --times-file; give one")


def read_stack_from_cli(images: List[Path], times: Optional[str], times_file: Optional[Path],
                         times_inverse: bool):
    from derender.io.exif import parse_times
    from derender.io.files import expand_image_paths
    from derender.io.images import read_stack

    check_times_options(times, times_file, times_inverse)
    images = expand_image_paths(images)
    t = parse_times(times) if times is not None else None
    return read_stack(images, times=t, times_file=times_file, times_file_inverse=times_inverse)


TIMES_HELP = "Exposure times in seconds, comma separated (default: EXIF ExposureTime)."
TIMES_FILE_HELP = "File of 'FILENAME SECONDS' lines."
INVERSE_HELP = "The times file's 2nd column is 1/time (HDRShop / Debevec image lists)."


def is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True




def read_radiance_map(path: Path) -> tuple:
    """A radiance map (.exr or .hdr) as ``(image, header, primaries)``: the .hdr's header lines
    (``VIEW``, ``EXPOSURE``, ...) or the EXR's header attributes, and the primaries its RGB is
    in: the .hdr's ``PRIMARIES`` line (None: Radiance's standard primaries), linear sRGB for an
    EXR (derender writes its maps in linear sRGB)."""
    from derender.io.rgbe import SRGB_PRIMARIES, read_hdr_header, read_radiance

    is_hdr = Path(path).suffix.lower() in (".hdr", ".pic")
    image = read_radiance(path)
    if is_hdr:
        header = read_hdr_header(path)
    else:
        from derender.io.exr import read_exr_attributes

        header = read_exr_attributes(path)
    primaries = header.get("PRIMARIES") if is_hdr else SRGB_PRIMARIES
    return image, header, primaries


def map_is_absolute(header: dict) -> bool:
    """Whether a map's header says it is in absolute units (cd/m2 = 179 w·RGB): an EXR's
    ``whiteLuminance`` or ``derender:photometry`` attribute, a .hdr's ``DERENDER_PHOTOMETRY=``
    line (what ``derender merge --spot``, ``--absolute exif`` or a ``--profile`` with a
    factor write). Any other map is relative: its scale is the camera's, not a luminance."""
    return any(k in header for k in ("whiteLuminance", "derender:photometry", "DERENDER_PHOTOMETRY"))


def map_summary(header: dict):
    """The merge's summary record a map's header holds (:mod:`derender.hdr.summary`), or None."""
    from derender.hdr.summary import SUMMARY_ATTRIBUTE, SUMMARY_HEADER, MergeSummary

    text = header.get(SUMMARY_ATTRIBUTE, header.get(SUMMARY_HEADER))
    return MergeSummary.from_json(text) if isinstance(text, str) else None


def absolute_units(header: dict, absolute: bool, relative: bool, path: Path) -> bool:
    """The units a map's luminance is labelled in: ``--absolute`` or ``--relative`` when given
    (not both), else what the map's header says (:func:`map_is_absolute`)."""
    if absolute and relative:
        raise InputError("give either --absolute or --relative, not both")
    if absolute or relative:
        return absolute
    return map_is_absolute(header)


def read_mask_codes(path: Path, option: str, shape: tuple | None = None):
    """The first channel of an 8-bit mask PNG (a merge's ``--mask``, a ghost mask), checked
    against the ``(H, W)`` ``shape`` of the map it belongs to."""
    from derender.io.images import read_codes

    codes = read_codes(path, max_megapixels=None)
    if codes is None or (shape is not None and codes.shape[:2] != tuple(shape)):
        raise InputError(f"{option} {path} is not an 8-bit mask" + (" of the map's size" if shape else ""))
    return codes[..., 0]


def check_model_camera(model_path: Path, image: Path, strict: bool) -> None:
    """Warn (one ``warning:`` line) or, ``strict``, refuse when a single model file was
    calibrated for another camera than the image's EXIF names."""
    if not Path(model_path).is_file():
        return   # a folder of models: resolve_model already picks the matching camera
    from derender.derendering.library import camera_mismatch, resolve_model

    model, _ = resolve_model(model_path, image)
    note = camera_mismatch(model, image)
    if note is None:
        return
    if strict:
        raise InputError(note + " (--strict-camera)")
    typer.echo(f"warning: {note}; its colours may not fit (--strict-camera makes this an error)", err=True)
