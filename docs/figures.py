"""The figures of the documentation, drawn with matplotlib when the docs are built.

``docs/conf.py`` calls :func:`draw_all`; run ``python docs/figures.py OUTDIR`` to draw them
by hand. Only matplotlib is needed (no graphviz binary), so the docs build on any machine
that can ``pip install -e '.[docs]'``.
"""

from __future__ import annotations

import sys
import tomllib
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import FancyArrowPatch, FancyBboxPatch  # noqa: E402

from derender.engine.motion.run import MotionOptions

__all__ = ["draw_dataflow", "import_layers", "draw_layers", "draw_ghosts", "draw_all"]

#: Fill colour per layer group (light, readable in print and on dark themes' white panels).
COLOURS = {
    "files": "#eeeeee",
    "io": "#dbe9f6",
    "camera": "#fde2c8",
    "raw": "#fde2c8",
    "model": "#e3f1dc",
    "engine": "#f9d5d3",
    "result": "#fff2b3",
    "out": "#e8dff5",
}
_SVG_META = {"Date": None, "Creator": None}


def _box(ax, x, y, w, h, title, body="", module="", kind="io", bold=False):
    """A rounded box centred at (x, y): bold ``title``, plain ``body``, ``module`` in monospace."""
    ax.add_patch(FancyBboxPatch((x - w / 2, y - h / 2), w, h, boxstyle="round,pad=0.25,rounding_size=0.8",
                                facecolor=COLOURS[kind], edgecolor="#444444", linewidth=1.6 if bold else 0.9))
    lines = [(title, {"fontweight": "bold", "fontsize": 9.5})]
    if body:
        lines += [(line, {"fontsize": 8}) for line in body.split("\n")]
    if module:
        lines += [(module, {"fontsize": 7.5, "family": "monospace", "color": "#1f4e8c"})]
    step = 2.1
    top = y + step * (len(lines) - 1) / 2
    for i, (text, style) in enumerate(lines):
        ax.text(x, top - i * step, text, ha="center", va="center", **style)


def _arrow(ax, start, end, text="", rad=0.0, style="-|>", colour="#333333", dashed=False, text_at=None):
    ax.add_patch(FancyArrowPatch(start, end, arrowstyle=style, mutation_scale=11, color=colour, linewidth=1.0,
                                 linestyle="--" if dashed else "-", connectionstyle=f"arc3,rad={rad}",
                                 shrinkA=2, shrinkB=2))
    if text:
        mx, my = text_at or ((start[0] + end[0]) / 2 + 0.6, (start[1] + end[1]) / 2)
        ax.text(mx, my, text, fontsize=7, style="italic", color="#333333", ha="left", va="center")


def _canvas(width_in: float, height_in: float, xmax: float, ymax: float):
    fig = plt.figure(figsize=(width_in, height_in))
    ax = fig.add_axes((0, 0, 1, 1))
    ax.set_xlim(0, xmax)
    ax.set_ylim(0, ymax)
    ax.axis("off")
    return fig, ax


def draw_dataflow(path: Path) -> Path:
    """Data flow: files in -> io -> per-frame models -> the one merge engine -> results -> files out."""
    fig, ax = _canvas(11, 9.6, 110, 96)
    # row 1: files in
    y1 = 85
    _box(ax, 14, y1, 24, 8, "8-bit images", "JPEG / PNG / TIFF, EXIF times", "io.images, io.exif", "files")
    _box(ax, 41, y1, 20, 8, "RAW / DNG frames", "bracket of the same scene", "io.raw", "files")
    _box(ax, 66, y1, 22, 8, "model file (.npz)", "from derender calibrate", "derendering", "files")
    _box(ax, 93, y1, 26, 8, "camera simulator", "spectral scene -> DNG + JPEG,\ntruth.exr, chart pairs", "camera",
         "camera")
    _arrow(ax, (86, y1 + 4.5), (45, y1 + 4.5), rad=0.12, dashed=True)
    _arrow(ax, (84, y1 + 4.5), (20, y1 + 4.5), "writes", rad=0.12, dashed=True, text_at=(50, 93.5))
    # row 2: io -> Stack; RAW development
    y2 = 68
    _box(ax, 22, y2, 36, 8, "Stack", "images (N,H,W,3) float32 or 8-bit codes,\nexposure times (s), metadata",
         "core.types (read by io)", "io", bold=True)
    _box(ax, 66, y2, 30, 8, "RAW development (paper 1, Alg. 2)",
         "binary-weight merge, white balance,\nMalvar demosaic -> linear sRGB", "raw.groundtruth", "raw")
    _arrow(ax, (14, y1 - 5), (18, y2 + 5))
    _arrow(ax, (41, y1 - 5), (58, y2 + 5))
    # row 3: per-frame models of the methods
    y3 = 49
    _box(ax, 14.5, y3, 26, 9, "response curves", "Debevec & Malik 1997,\nRobertson 2003: g(z) per channel",
         "response", "model")
    _box(ax, 42, y3, 27, 9, "stabilisation (paper 1)", "reference, alignment, gamma_j,\n3x3 matrices H_j",
         "hdr.stabilize, hdr.align", "model")
    _box(ax, 71, y3, 27, 9, "de-rendering models (paper 2)", "GP / poly / RBF: code ->\nmean, variance of RAW colour",
         "derendering", "model")
    for x in (14, 42, 60):
        _arrow(ax, (22 + (x - 22) * 0.4, y2 - 5), (x, y3 + 5.5))
    _arrow(ax, (66, y1 - 5), (78, y3 + 5.5), rad=-0.25)
    # row 4: the one merge engine
    y4 = 31
    _box(ax, 44, y4, 66, 9, "the merge engine (one for every method)",
         "a method gives, per frame: 256-entry value / weight tables, an optional 3x3 matrix, a noise model;\n"
         "the engine decodes frames in threads, applies alignment shifts, accumulates in bands, saturation policy",
         "hdr.registry / hdr.files -> engine", "engine", bold=True)
    for x in (14, 42, 71):
        _arrow(ax, (x, y3 - 5.5), (x if x != 71 else 66, y4 + 5.5))
    _arrow(ax, (7, y2 - 4), (13, y4 + 5.5), "codes", rad=0.35, text_at=(0.3, 40))
    # row 5: the result
    y5 = 16
    _box(ax, 44, y5, 46, 7, "HDRResult", "radiance (H,W,3) float32 linear  +  variance  +  mask (0 ok, 1 bright, 2 dark)",
         "core.types", "result", bold=True)
    _arrow(ax, (44, y4 - 5.5), (44, y5 + 4.5))
    # row 6: files out
    y6 = 4
    _box(ax, 12, y6, 20, 6, "EXR files", "radiance, variance", "io.exr", "out")
    _box(ax, 34, y6, 20, 6, "PNG previews", "tone-mapped, mask", "io.preview", "out")
    _box(ax, 60, y6, 26, 6, "evaluation", "PSNR R/G/B/L, paper tables", "evaluation", "out")
    _box(ax, 91, y6, 28, 6, "applications", "photometric stereo: normals, depth", "applications", "out")
    for x in (12, 34, 60):
        _arrow(ax, (44 + (x - 44) * 0.3, y5 - 4), (x, y6 + 3.5))
    _arrow(ax, (81, y2 - 5), (70, y6 + 3.5), "ground truth", rad=-0.15, text_at=(86.5, 24))
    _arrow(ax, (84, y3 - 5.5), (91, y6 + 3.5), "mean, variance\nper pixel", rad=-0.1, text_at=(97, 28))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, metadata=_SVG_META if path.suffix == ".svg" else None, dpi=110)
    plt.close(fig)
    return path


#: What each stage is for, beside its box in the layer figure.
LAYER_TEXT = {
    "cli": "command-line interface (typer)",
    "evaluation": "PSNR protocol, paper tables, diagnostics",
    "applications": "photometric stereo",
    "hdr": "merge methods, registry, merging files",
    "derendering": "p(RAW colour | JPEG colour) models",
    "response": "Debevec 1997, Robertson 2003",
    "engine": "merge engine",
    "camera": "simulator",
    "raw": "RAW development",
    "io": "file formats",
    "core": "types, errors, colorimetry, lazy re-exports",
}


def import_layers(pyproject: Path = Path(__file__).resolve().parent.parent / "pyproject.toml") -> list[list[str]]:
    """The layers of the import-linter contract in ``pyproject.toml``, top to bottom (names without ``derender.``)."""
    with open(pyproject, "rb") as fh:
        contracts = tomllib.load(fh)["tool"]["importlinter"]["contracts"]
    layers = next(c["layers"] for c in contracts if c.get("type") == "layers")
    return [[name.strip().removeprefix("derender.") for name in layer.split("|")] for layer in layers]


def draw_layers(path: Path) -> Path:
    """The import layers: a module imports only from layers below its own."""
    layers = import_layers()
    top = 5.6 * len(layers)
    fig, ax = _canvas(7.5, 0.6 * len(layers) + 0.2, 75, top + 5.6)
    y = top + 0.6
    for names in layers:
        text = " | ".join(LAYER_TEXT.get(n, "") for n in names)
        width = 40 / len(names)
        for i, name in enumerate(names):
            x = 6 + width * i + width / 2
            ax.add_patch(FancyBboxPatch((x - width / 2 + 0.4, y - 2.2), width - 0.8, 4.4,
                                        boxstyle="round,pad=0.1,rounding_size=0.6", facecolor=COLOURS["io"],
                                        edgecolor="#444444", linewidth=0.9))
            ax.text(x, y, f"derender.{name}" if len(names) == 1 else name, ha="center", va="center",
                    fontsize=8.5, family="monospace")
        ax.text(48, y, text, ha="left", va="center", fontsize=8)
        y -= 5.6
    _arrow(ax, (3, top + 1.6), (3, 5.6), style="-|>")
    ax.text(1.6, top / 2 + 3, "imports go down only", rotation=90, ha="center", va="center", fontsize=8, style="italic")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, metadata=_SVG_META if path.suffix == ".svg" else None, dpi=110)
    plt.close(fig)
    return path


def draw_ghosts(path: Path) -> Path:
    """Before and after ghost removal on a simulated handheld bracket with moving objects
    (192x128, 7 exposures, camera family, seed 0): the reference frame, the stabilised merge
    without and with ``align="translation", deghost=True``, the frames left out per pixel and
    the truth; every map scaled to the truth by one factor and tone-mapped alike (Reinhard, the
    truth's 99th percentile as white)."""
    import numpy as np

    import derender as dr
    from derender.camera import simulate_bracket
    from derender.camera.motion import MotionSpec
    from derender.core.types import Stack

    b = simulate_bracket("nikon-d5100", kind="outdoor", size=(192, 128), exposures=7, seed=0, family="camera",
                         motion=MotionSpec(objects=3, shake=4))
    ref = b.params["motion"]["reference"]
    stack = Stack(images=b.jpeg_codes.astype(np.float32) / np.float32(255), times=b.times)
    plain = dr.merge(stack, "stabilized", motion=MotionOptions(reference=ref))
    clean = dr.merge(stack, "stabilized", motion=MotionOptions(reference=ref, align="translation", deghost=True))
    truth = b.truth_linear_srgb

    def fitted(r):          # one scale to the truth (median luminance ratio): the maps as the method gives them
        k = np.median(truth.mean(axis=-1)) / max(float(np.median(r.mean(axis=-1))), 1e-12)
        return r * k

    white = float(np.percentile(truth, 99))

    def tone(x):
        x = x / white
        return np.clip(x / (1 + x), 0, 1) ** (1 / 2.2)

    panels = [(b.jpeg_codes[ref] / 255.0, "reference frame (JPEG)"), (tone(fitted(plain.radiance)), "stabilized"),
              (tone(fitted(clean.radiance)), "stabilized, --align translation --deghost"),
              (clean.ghosts / max(int(clean.ghosts.max()), 1), "frames left out (ghost mask)"),
              (tone(truth), "truth at the reference instant")]
    fig, axes = plt.subplots(1, len(panels), figsize=(13.5, 2.35))
    for ax, (img, title) in zip(axes, panels):
        ax.imshow(img, cmap="gray" if img.ndim == 2 else None, vmin=0, vmax=1, interpolation="nearest")
        ax.set_title(title, fontsize=8.5)
        ax.axis("off")
    fig.tight_layout(pad=0.3)
    fig.savefig(path, dpi=110, metadata={"Software": None})
    plt.close(fig)
    return path


def draw_all(outdir: Path) -> list[Path]:
    """Draw every figure into ``outdir`` (``dataflow.svg``, ``layers.svg``, ``ghosts.png``,
    ``reliability.png``: :func:`reliability.draw_reliability`, from the coverages measured by
    ``python docs/reliability.py --measure``)."""
    from reliability import draw_reliability

    with plt.rc_context({"svg.hashsalt": "derender", "font.family": "DejaVu Sans"}):
        return [draw_dataflow(Path(outdir) / "dataflow.svg"), draw_layers(Path(outdir) / "layers.svg"),
                draw_ghosts(Path(outdir) / "ghosts.png"), draw_reliability(Path(outdir) / "reliability.png")]


if __name__ == "__main__":
    for p in draw_all(Path(sys.argv[1] if len(sys.argv) > 1 else "docs/_generated")):
        print(p)
