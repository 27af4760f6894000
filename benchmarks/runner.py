"""The side-by-side merge benchmark: OpenCV, colour-hdri and ``derender merge`` in fresh processes.

Not part of the installed package (issue 14): the benchmark scripts in this folder import it
(``bench_merge.py`` is its command line). :func:`generate_bench_bracket` makes and caches a
bracket; :func:`run_bench` runs every entry on the same files and measures wall time, the
tool's own time, peak RSS and CPU time; :func:`format_bench` prints the table.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from derender.core.errors import InputError
from derender.core.memory import thread_count

__all__ = [
    "generate_bench_bracket",
    "method_registered",
    "run_bench",
    "format_bench",
]


# --------------------------------------------------------------------------- benchmark
def _scene_texture(w: int, h: int, rng: np.random.Generator) -> np.ndarray:
    """A log-normal multi-scale texture (H, W) float32 around 1: octaves of cubic-upscaled
    Gaussian noise from 8 px to full resolution, the same in every frame (scene detail,
    not noise), so that every exposure carries detail at every scale like a photograph."""
    import cv2

    acc = np.zeros((h, w), dtype=np.float32)
    for cells, amp in ((8, 0.25), (32, 0.15), (128, 0.12), (512, 0.10), (2048, 0.08), (1 << 30, 0.06)):
        sw = min(w, cells)
        sh = max(2, int(round(sw * h / w)))
        acc += np.float32(amp) * cv2.resize(rng.standard_normal((sh, sw), dtype=np.float32), (w, h),
                                            interpolation=cv2.INTER_CUBIC)
    return np.exp(acc, out=acc)


#: Width at which ``texture="scene"`` brackets are simulated (the texture then has detail down to
#: 4 px of a 6000-wide frame; 19 s and 0.7 GB for 9 frames).
SCENE_SIM_WIDTH = 1536


def generate_bench_bracket(workdir: str | os.PathLike, size: tuple[int, int] = (6000, 4000), frames: int = 9,
                           seed: int = 0, sim_width: int = 768, grain: int = 2, quality: int = 95,
                           camera: str = "nikon-d5100", texture: bool | str = True) -> list[Path]:
    """JPEG bracket of ``size`` (W, H) written with EXIF times by :func:`derender.camera.write_jpeg`
    (quality 95, 4:2:2). Cached in ``workdir/bracket-WxH-N-sSEED[-tex]`` (reused when complete).

    The simulator (:func:`derender.camera.simulate_bracket`) renders the bracket ``sim_width``
    wide; every frame is upscaled (bicubic). With ``texture`` (the default) the upscaled
    frames get realistic entropy: the scene is multiplied (in linear light, gamma 2.2) by a
    multi-scale texture that is the same in every exposure (:func:`_scene_texture`, detail
    at every scale up to single pixels), then per-frame Gaussian noise of 1-3 codes is added
    (more in the shadows, as a sensor's read noise): a 24 MP frame compresses to 4-9 MB and
    decodes as slowly as a camera JPEG of that size (see ``benchmarks/README.md``). Without
    it, uniform grain of +-``grain`` codes (the bracket of issues 8-15: ~3 MB per 24 MP frame,
    decoding unrealistically fast).

    The texture of ``texture=True`` is not physically consistent: it multiplies every frame's
    *codes* in gamma-2.2 light, whereas the camera's tone curve is not a 2.2 power and differs
    between the auto pipeline's frames, so the same scene detail has a different radiance
    contrast in every exposure. Measured at the simulator's size (768x512, 9 exposures, seed 0):
    the recipe's codes differ from the camera's rendering of the same texture put in the scene
    by a median 2-9 codes (90th percentile 6-25) per frame, and ghost removal rejects 5.6 %
    (Debevec) and 12.5 % (stabilised) of a bracket where nothing moves, against 0.8 % and 0.2 %
    with the texture in the scene. ``texture="scene"`` is that consistent bracket at full size:
    the same texture multiplies the scene's radiance on the sensor (the simulator's ``falloff``)
    of a bracket rendered :data:`SCENE_SIM_WIDTH` wide, then every frame is upscaled and gets
    the same per-frame noise (folder suffix ``-scene``).
    """
    import cv2

    from derender.camera import simulate_bracket, write_jpeg

    w, h = int(size[0]), int(size[1])
    if w < 16 or h < 16 or frames < 2:
        raise InputError("bench bracket needs at least 16x16 pixels and 2 frames")
    scene_texture = texture == "scene"
    suffix = "-scene" if scene_texture else ("-tex" if texture else "")
    folder = Path(workdir) / (f"bracket-{w}x{h}-{frames}-s{seed}" + suffix)
    done = folder / "bracket.json"
    if done.is_file():
        meta = json.loads(done.read_text())
        paths = [folder / name for name in meta["files"]]
        if all(p.is_file() for p in paths):
            return paths
    folder.mkdir(parents=True, exist_ok=True)
    sw = min(SCENE_SIM_WIDTH if scene_texture else sim_width, w)
    sh = max(16, int(round(sw * h / w)))
    rng = np.random.default_rng(seed + 12345)
    falloff = _scene_texture(sw, sh, rng).astype(np.float64) if scene_texture else None
    bracket = simulate_bracket(camera=camera, size=(sw, sh), exposures=frames, seed=seed, falloff=falloff)
    if scene_texture:
        tex = None
        noise = None
    elif texture:
        tex = _scene_texture(w, h, rng)[..., None]
        to_lin = ((np.arange(256) / 255.0) ** 2.2).astype(np.float32)
        noise = None
    else:
        tex = None
        noise = rng.integers(-grain, grain + 1, size=(h, w, 3), dtype=np.int16) if grain > 0 else None
    paths = []
    for j, t in enumerate(bracket.times):
        big = cv2.resize(bracket.jpeg_codes[j], (w, h), interpolation=cv2.INTER_CUBIC)
        if tex is not None:
            g = to_lin[big]
            g *= tex
            np.clip(g, 0.0, 1.0, out=g)
            g **= np.float32(1 / 2.2)
            g *= np.float32(255.0)
            sigma = np.float32(3.0) - g * np.float32(2.0 / 255.0)
            g += rng.standard_normal((h, w, 3), dtype=np.float32) * sigma
            del sigma
            big = np.clip(g + np.float32(0.5), 0, 255).astype(np.uint8)
            del g
        elif noise is not None:
            big = np.clip(big.astype(np.int16) + np.roll(noise, 7 * j, axis=0), 0, 255).astype(np.uint8)
        elif scene_texture:        # the texture is in the scene: only the per-frame noise of the recipe above
            g = big.astype(np.float32)
            sigma = np.float32(3.0) - g * np.float32(2.0 / 255.0)
            g += rng.standard_normal((h, w, 3), dtype=np.float32) * sigma
            del sigma
            big = np.clip(g + np.float32(0.5), 0, 255).astype(np.uint8)
            del g
        paths.append(write_jpeg(folder / f"{j:02d}.jpg", big, float(t), bracket.camera.make, bracket.camera.model,
                                quality=quality))
        del big
    done.write_text(json.dumps({"size": [w, h], "frames": frames, "seed": seed, "grain": grain, "texture": texture,
                                "times": [float(x) for x in bracket.times], "files": [p.name for p in paths]}))
    return paths


_OPENCV_WORKER = r"""
import json, sys, time
t0 = time.perf_counter()
import cv2, numpy as np
from derender.io.exif import read_exposure_time
algo, paths = sys.argv[1], sys.argv[2:]
times = np.array([read_exposure_time(p) for p in paths], dtype=np.float32)
t1 = time.perf_counter()
imgs = [cv2.imread(p) for p in paths]
t2 = time.perf_counter()
if algo == "robertson":
    resp = cv2.createCalibrateRobertson().process(imgs, times)
    t3 = time.perf_counter()
    hdr = cv2.createMergeRobertson().process(imgs, times, resp)
else:
    resp = cv2.createCalibrateDebevec().process(imgs, times)
    t3 = time.perf_counter()
    hdr = cv2.createMergeDebevec().process(imgs, times, resp)
t4 = time.perf_counter()
print(json.dumps({"inner_s": t4 - t1, "decode_s": t2 - t1, "calibrate_s": t3 - t2, "merge_s": t4 - t3,
                  "threads": cv2.getNumThreads(), "finite": bool(np.isfinite(hdr).all())}))
"""


#: The floor: what any merge of these files into this EXR must do at least -- decode every
#: frame once with derender's decoder and thread count (:func:`derender.engine.frames.read_frames`)
#: and write a radiance map of the same content with the same writer and options. The image
#: written is a merged output read beforehand (outside the timing, ``read_s``, subtracted from
#: the wall time by the runner), so its compression costs what the merge's output costs.
_FLOOR_WORKER = r"""
import json, sys, time
t0 = time.perf_counter()
from pathlib import Path
import numpy as np
from derender.engine.frames import read_frames
from derender.io.exr import read_exr, write_exr_fast
like, out, paths = sys.argv[1], sys.argv[2], [Path(p) for p in sys.argv[3:]]
tr = time.perf_counter()
img = read_exr(like)
read_s = time.perf_counter() - tr
t1 = time.perf_counter()
frames, _ = read_frames(paths, None)
t2 = time.perf_counter()
write_exr_fast(out, img)
t3 = time.perf_counter()
print(json.dumps({"inner_s": t3 - t1, "decode_s": t2 - t1, "write_s": t3 - t2, "read_s": read_s,
                  "exr_mb": Path(out).stat().st_size / 1e6}))
"""


_COLOUR_HDRI_WORKER = r"""
import json, sys, time
try:
    import colour_hdri
except ImportError as exc:
    print(json.dumps({"status": "skipped", "reason": f"colour_hdri not importable ({exc})"}))
    sys.exit(0)
t1 = time.perf_counter()
try:
    from colour_hdri import (ImageStack, camera_response_functions_Debevec1997, image_stack_to_HDRI,
                             weighting_function_Debevec1997)
    stack = ImageStack.from_files(sys.argv[1:])
    crfs = camera_response_functions_Debevec1997(stack)
    hdri = image_stack_to_HDRI(stack, weighting_function_Debevec1997, crfs)
except Exception as exc:
    print(json.dumps({"status": "error", "reason": f"{type(exc).__name__}: {exc}"}))
    sys.exit(0)
print(json.dumps({"inner_s": time.perf_counter() - t1}))
"""


#: Runs a Python child (``-c CODE`` or ``-m MODULE`` and its arguments) and reports, at its exit, its
#: own peak RSS (``VmHWM`` of ``/proc/self/status``). The parent cannot ask the kernel: a forked
#: child's ``ru_maxrss`` (``wait4``) starts from the parent's RSS at fork and keeps it through exec,
#: so every small child reported the benchmark runner's own ~290 MB (issue 15).
_PEAK_WRAPPER = r"""
import atexit, runpy, sys

def _peak():
    try:
        with open("/proc/self/status") as fh:
            kb = next(int(line.split()[1]) for line in fh if line.startswith("VmHWM:"))
        sys.stderr.write(f"\n__DERENDER_PEAK_RSS_KB__ {kb}\n")
        sys.stderr.flush()
    except (OSError, StopIteration):
        pass

atexit.register(_peak)
mode, target, *rest = sys.argv[1:]
if mode == "-m":
    sys.argv = [target, *rest]
    runpy.run_module(target, run_name="__main__", alter_sys=True)
else:
    sys.argv = ["-c", *rest]
    exec(compile(target, "<benchmark worker>", "exec"), {"__name__": "__main__"})
"""


def peak_rss_kb(stderr: str) -> int | None:
    """The child's own peak RSS (kB) reported by :data:`_PEAK_WRAPPER`, or None."""
    import re

    found = re.findall(r"__DERENDER_PEAK_RSS_KB__ (\d+)", stderr)
    return int(found[-1]) if found else None


def _run_measured(cmd: list[str], cwd: str | os.PathLike | None = None, env: dict | None = None) -> dict:
    """Run ``cmd``; wall time, exit code, stdout/stderr tails, CPU time (``wait4``) and the peak RSS.

    A Python child (``python -c CODE ...`` or ``python -m MODULE ...``) runs under
    :data:`_PEAK_WRAPPER`, which reports the child's own ``VmHWM``; other commands fall back
    to ``wait4``'s ``ru_maxrss``, which includes the runner's RSS at fork time."""
    wrapped = (len(cmd) >= 3 and cmd[1] in ("-c", "-m"))
    run_cmd = [cmd[0], "-c", _PEAK_WRAPPER, *cmd[1:]] if wrapped else cmd
    with tempfile.TemporaryFile() as fo, tempfile.TemporaryFile() as fe:
        t0 = time.perf_counter()
        proc = subprocess.Popen(run_cmd, stdout=fo, stderr=fe, cwd=cwd, env=env)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        fo.seek(0)
        fe.seek(0)
        out = fo.read().decode("utf-8", "replace")
        err = fe.read().decode("utf-8", "replace")
    own = peak_rss_kb(err) if wrapped else None
    err = err.replace(f"\n__DERENDER_PEAK_RSS_KB__ {own}\n", "\n") if own is not None else err
    # MB = 1e6 bytes, the unit of the RSS target (codes + outputs in bytes / 1e6); VmHWM and
    # ru_maxrss are in KiB. Until issue 17's third session this divided by 1024 (MiB) and
    # compared MiB with a target in MB: every peak quoted before then is 4.9 % low.
    peak = (own if own is not None else usage.ru_maxrss) * 1024.0 / 1e6
    return {"returncode": proc.returncode, "wall_s": wall, "peak_rss_mb": peak,
            "peak_rss_source": "VmHWM (child)" if own is not None else "wait4 ru_maxrss",
            "cpu_s": usage.ru_utime + usage.ru_stime, "stdout": out[-2000:], "stderr": err[-2000:]}


def _last_json(text: str) -> dict:
    for line in reversed(text.strip().splitlines()):
        line = line.strip()
        if line.startswith("{"):
            try:
                return json.loads(line)
            except json.JSONDecodeError:
                continue
    return {}


#: Methods whose ``derender merge`` needs a de-rendering model (``-m``).
MODEL_METHODS = ("probabilistic", "stabilized-probabilistic")


def bench_model(workdir: str | os.PathLike, seed: int = 0) -> Path:
    """A GP de-rendering model for the probabilistic methods (5000 simulated D5100 chart
    pairs), fitted once and cached in ``workdir``."""
    from derender.core.errors import DerenderError
    from derender.derendering.base import fit_model, load_model, model_camera_to_srgb, model_metadata

    model = Path(workdir) / "nikon-d5100-gp.npz"
    try:
        if model_camera_to_srgb(load_model(model)) is not None:
            return model
    except DerenderError:          # missing, or written by another model-file version
        pass
    model.unlink(missing_ok=True)
    from derender.camera.chart import chart_pairs

    pairs = chart_pairs("nikon-d5100")
    train = np.random.default_rng(seed).permutation(len(pairs.jpeg))[:5000]
    fit_model("gp", pairs.jpeg[train], pairs.raw[train], seed=seed, metadata=model_metadata(pairs)).save(model)
    return model


def _bench_one(name: str, paths: list[Path], outdir: Path, python: str, model: Path | None = None,
               like: Path | None = None) -> dict:
    files = [str(p) for p in paths]
    if name in ("opencv", "opencv-debevec", "opencv-robertson"):
        cmd = [python, "-c", _OPENCV_WORKER, "robertson" if name.endswith("robertson") else "debevec", *files]
    elif name == "colour-hdri":
        cmd = [python, "-c", _COLOUR_HDRI_WORKER, *files]
    elif name == "floor":
        if like is None:
            return {"status": "skipped", "reason": "needs a merged output to write (run a derender entry first)"}
        cmd = [python, "-c", _FLOOR_WORKER, str(like), str(outdir / f"floor-{len(paths)}.exr"), *files]
    elif name.startswith("derender-"):
        method, *extras = name[len("derender-"):].split("+")
        cmd = [python, "-m", "derender.cli", "merge", *files, "-o", str(outdir / f"{name}-{len(paths)}.exr"),
               "--method", method]
        for extra in extras:        # derender-METHOD+align, +deghost: the engine's motion steps
            if extra == "align":
                cmd += ["--align", "translation"]
            elif extra == "deghost":
                cmd += ["--align", "translation", "--deghost"]
            else:
                raise InputError(f"unknown benchmark entry suffix +{extra} (use +align or +deghost)")
        if method in MODEL_METHODS:
            if model is None:
                return {"status": "skipped", "reason": "needs a de-rendering model"}
            cmd += ["-m", str(model)]
    else:
        raise InputError(f"unknown benchmark entry {name!r}")
    run = _run_measured(cmd)
    detail = _last_json(run["stdout"])
    status = detail.pop("status", "ok" if run["returncode"] == 0 else "error")
    if name == "floor" and "read_s" in detail:
        run["wall_s"] -= detail["read_s"]       # reading the image to write is not part of the floor
    row = {"status": status, "command": " ".join([Path(cmd[0]).name, *cmd[1:2]] if cmd[1] == "-c" else
                                                  [Path(cmd[0]).name, *cmd[1:5], "...", *cmd[-4:]]),
           "wall_s": run["wall_s"], "peak_rss_mb": run["peak_rss_mb"], "cpu_s": run["cpu_s"], **detail}
    if name.startswith("derender-") and run["returncode"] == 0:
        import re

        m = re.search(r"\(([0-9.]+) s;", run["stdout"])
        if m:
            row["inner_s"] = float(m.group(1))
        out = outdir / f"{name}-{len(paths)}.exr"
        if out.is_file():
            row["exr_mb"] = out.stat().st_size / 1e6
    if status == "error":
        row["reason"] = (detail.get("reason") or run["stderr"].strip().splitlines()[-1:] or ["?"])
    return row


def method_registered(method: str) -> bool:
    from derender.core.errors import InputError
    from derender.hdr.registry import get_method

    try:
        get_method(method)
    except InputError:
        return False
    return True


def _median(xs: Sequence[float]) -> float:
    return float(np.median(np.asarray(xs, dtype=np.float64)))


def run_bench(size: tuple[int, int] = (6000, 4000), frames: int = 9, workdir: str | os.PathLike | None = None,
              entries: Sequence[str] | None = None, memory_frames: int | None = None, seed: int = 0,
              repeat: int = 1, python: str | None = None, progress: Callable[[str], None] | None = None,
              texture: bool | str = True, model: str | os.PathLike | None = None) -> dict:
    """Side-by-side benchmark on a generated bracket (:func:`generate_bench_bracket`), each run in a fresh process.

    ``entries`` (default floor, OpenCV, derender's Debevec and stabilised merges):
    ``"floor"`` (decode every frame once + write the same EXR: :data:`_FLOOR_WORKER`; it
    writes the output of the first derender entry, so one is needed), ``"opencv"`` /
    ``"opencv-robertson"`` (cv2.imread x N + OpenCV's calibration and merge, no file
    written), ``"colour-hdri"`` (skipped when not importable) and ``"derender-METHOD"``
    (the ``derender merge`` command: decode, calibrate, merge and EXR write; the
    probabilistic methods get ``model`` or a cached GP model, :func:`bench_model`).
    ``repeat`` rounds run every entry in turn (alternating, so slow phases of a loaded
    machine hit all entries); a row gives the median over the rounds, and every ratio is
    the median over the rounds of the two entries' same-round ratio. With
    ``memory_frames`` (e.g. 18) ``derender merge --method debevec`` also runs on a bracket of
    that many frames, to compare peak RSS. Wall time is the whole process (interpreter
    start included); ``inner_s`` the tool's own timing; peak RSS the child's own VmHWM.
    Returns a dict (see :func:`format_bench`).
    """
    python = python or sys.executable
    workdir = Path(workdir) if workdir is not None else Path(tempfile.gettempdir()) / "derender-bench"
    workdir.mkdir(parents=True, exist_ok=True)
    say = progress or (lambda msg: None)
    if entries is None:
        entries = ["floor", "opencv", "derender-debevec", "derender-stabilized"]
    entries = list(entries)
    if "floor" in entries:     # the floor writes a derender output: run one before it
        first = next((e for e in entries if e.startswith("derender-")), None)
        if first is not None:
            entries.remove("floor")
            entries.insert(entries.index(first) + 1, "floor")
    say(f"generating {frames} frames {size[0]}x{size[1]} in {workdir} (cached)")
    paths = generate_bench_bracket(workdir, size, frames, seed, texture=texture)
    outdir = workdir / "outputs"
    outdir.mkdir(exist_ok=True)
    need_model = any(e.startswith("derender-") and e[len("derender-"):].split("+")[0] in MODEL_METHODS for e in entries)
    model_path = Path(model) if model is not None else (bench_model(workdir, seed) if need_model else None)
    rounds: dict[str, list[dict]] = {name: [] for name in entries}
    skipped: dict[str, dict] = {}
    like = None
    for r in range(max(1, int(repeat))):
        for name in entries:
            if name in skipped:
                continue
            if name.startswith("derender-") and not method_registered(name[len("derender-"):].split("+")[0]):
                skipped[name] = {"status": "skipped", "reason": f"method {name[len('derender-'):]!r} is not registered"}
                continue
            say(f"round {r + 1}: running {name}")
            row = _bench_one(name, paths, outdir, python, model=model_path, like=like)
            if row["status"] != "ok":
                skipped[name] = row
                continue
            rounds[name].append(row)
            if like is None and name.startswith("derender-"):
                like = outdir / f"{name}-{len(paths)}.exr"
    runs: dict[str, dict] = {}
    for name in entries:
        if name in skipped and not rounds[name]:
            runs[name] = skipped[name]
            continue
        rows = rounds[name]
        med = dict(rows[0])
        for key in ("wall_s", "inner_s", "peak_rss_mb", "cpu_s", "decode_s", "write_s", "merge_s", "calibrate_s"):
            if all(key in x for x in rows):
                med[key] = _median([x[key] for x in rows])
        med["walls"] = [x["wall_s"] for x in rows]
        runs[name] = med
    result: dict[str, Any] = {
        "size": [int(size[0]), int(size[1])], "frames": int(frames), "workdir": str(workdir),
        "input_mb": sum(p.stat().st_size for p in paths) / 1e6,
        "frame_mb": [p.stat().st_size / 1e6 for p in paths], "texture": texture if isinstance(texture, str) else bool(texture),
        "cpus": thread_count(None), "load_avg": list(os.getloadavg()), "rounds": max(1, int(repeat)),
        "runs": runs, "ratios": {},
    }

    def ratio(a: str, b: str) -> float | None:
        ra, rb = rounds.get(a) or [], rounds.get(b) or []
        if not ra or len(ra) != len(rb):
            return None
        return _median([x["wall_s"] / y["wall_s"] for x, y in zip(ra, rb)])

    def cpu_ratio(a: str, b: str) -> float | None:
        ra, rb = rounds.get(a) or [], rounds.get(b) or []
        if not ra or len(ra) != len(rb):
            return None
        return _median([x["cpu_s"] / y["cpu_s"] for x, y in zip(ra, rb)])

    result["cpu_ratios"] = {}
    for ref in ("floor", "opencv", "derender-debevec"):
        for k in entries:
            if k != ref and not (ref == "derender-debevec" and not k.startswith("derender-")):
                v = ratio(k, ref)
                if v is not None:
                    result["ratios"][f"{k} / {ref}"] = v
                v = cpu_ratio(k, ref)
                if v is not None:
                    result["cpu_ratios"][f"{k} / {ref}"] = v
    if memory_frames:
        say(f"generating {memory_frames} frames for the memory comparison")
        big = generate_bench_bracket(workdir, size, int(memory_frames), seed, texture=texture)
        say(f"running derender-debevec on {memory_frames} frames")
        row = _bench_one("derender-debevec", big, outdir, python)
        base = runs.get("derender-debevec") or _bench_one("derender-debevec", paths, outdir, python)
        result["memory"] = {"frames": [int(frames), int(memory_frames)],
                            "peak_rss_mb": [base.get("peak_rss_mb"), row.get("peak_rss_mb")],
                            "wall_s": [base.get("wall_s"), row.get("wall_s")], "status": row["status"]}
        if row["status"] == "ok" and base.get("status") == "ok":
            result["memory"]["rss_ratio"] = row["peak_rss_mb"] / base["peak_rss_mb"]
    return result


def format_bench(result: dict) -> str:
    """Markdown table of a :func:`run_bench` result (medians over the rounds; ratios are
    medians of same-round ratios)."""
    w, h = result["size"]
    n = result["frames"]
    codes_mb = n * w * h * 3 / 1e6
    out_mb = w * h * (12 + 1) / 1e6          # float32 RGB radiance + uint8 mask
    fmb = result.get("frame_mb") or []
    lines = [f"{n} JPEGs {w}x{h} ({w * h / 1e6:.1f} MP, {result['input_mb']:.0f} MB"
             + (f", {min(fmb):.1f}-{max(fmb):.1f} MB per frame" if fmb else "") + f"), {result['cpus']} CPUs, "
             f"load average {result['load_avg'][0]:.2f}, median of {result.get('rounds', 1)} alternating round(s)",
             f"8-bit codes {codes_mb:.0f} MB + outputs {out_mb:.0f} MB = {codes_mb + out_mb:.0f} MB "
             f"(RSS target +25 %: {1.25 * (codes_mb + out_mb):.0f} MB)", "",
             "| tool | status | wall s | inner s | peak RSS MB | CPU s | EXR MB | vs floor | vs OpenCV | vs Debevec "
             "| CPU vs floor | CPU vs Debevec |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    rat = result.get("ratios", {})
    for name, r in result["runs"].items():
        if r.get("status") != "ok":
            lines.append(f"| {name} | {r.get('status')}: {r.get('reason', '')} | | | | | | | | | | |")
            continue
        inner = f"{r['inner_s']:.2f}" if "inner_s" in r else ""
        exr = f"{r['exr_mb']:.0f}" if "exr_mb" in r else ""
        cols = []
        for ref in ("floor", "opencv", "derender-debevec"):
            v = rat.get(f"{name} / {ref}")
            cols.append(f"{v:.2f}x" if v is not None else "")
        for ref in ("floor", "derender-debevec"):
            v = result.get("cpu_ratios", {}).get(f"{name} / {ref}")
            cols.append(f"{v:.2f}x" if v is not None else "")
        lines.append(f"| {name} | ok | {r['wall_s']:.2f} | {inner} | {r['peak_rss_mb']:.0f} | {r['cpu_s']:.1f} | "
                     f"{exr} | {' | '.join(cols)} |")
    fl = result["runs"].get("floor", {})
    if fl.get("status") == "ok" and "decode_s" in fl:
        lines.append(f"\nfloor: decode {fl['decode_s']:.2f} s + write {fl['write_s']:.2f} s")
    mem = result.get("memory")
    if mem:
        a, b = mem["frames"]
        ra, rb = mem["peak_rss_mb"]
        txt = f"\nmemory: derender-debevec peak RSS {a} frames {ra:.0f} MB, {b} frames {rb:.0f} MB"
        if "rss_ratio" in mem:
            txt += f" (ratio {mem['rss_ratio']:.2f})"
        lines.append(txt)
    return "\n".join(lines)
