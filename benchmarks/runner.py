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
def generate_bench_bracket(workdir: str | os.PathLike, size: tuple[int, int] = (6000, 4000), frames: int = 9,
                           seed: int = 0, sim_width: int = 768, grain: int = 2, quality: int = 95,
                           camera: str = "nikon-d5100") -> list[Path]:
    """JPEG bracket of ``size`` (W, H): simulator frames (:func:`derender.camera.simulate_bracket`,
    ``sim_width`` wide) upscaled with bicubic interpolation, plus uniform grain of
    +-``grain`` codes (deterministic) so the files compress like photographs, written
    with EXIF times by :func:`derender.camera.write_jpeg`. Cached in
    ``workdir/bracket-WxH-N-sSEED`` (reused when complete).
    """
    import cv2

    from derender.camera import simulate_bracket, write_jpeg

    w, h = int(size[0]), int(size[1])
    if w < 16 or h < 16 or frames < 2:
        raise InputError("bench bracket needs at least 16x16 pixels and 2 frames")
    folder = Path(workdir) / f"bracket-{w}x{h}-{frames}-s{seed}"
    done = folder / "bracket.json"
    if done.is_file():
        meta = json.loads(done.read_text())
        paths = [folder / name for name in meta["files"]]
        if all(p.is_file() for p in paths):
            return paths
    folder.mkdir(parents=True, exist_ok=True)
    sw = min(sim_width, w)
    sh = max(16, int(round(sw * h / w)))
    bracket = simulate_bracket(camera=camera, size=(sw, sh), exposures=frames, seed=seed)
    rng = np.random.default_rng(seed + 12345)
    noise = rng.integers(-grain, grain + 1, size=(h, w, 3), dtype=np.int16) if grain > 0 else None
    paths = []
    for j, t in enumerate(bracket.times):
        big = cv2.resize(bracket.jpeg_codes[j], (w, h), interpolation=cv2.INTER_CUBIC)
        if noise is not None:
            big = np.clip(big.astype(np.int16) + np.roll(noise, 7 * j, axis=0), 0, 255).astype(np.uint8)
        paths.append(write_jpeg(folder / f"{j:02d}.jpg", big, float(t), bracket.camera.make, bracket.camera.model,
                                quality=quality))
        del big
    done.write_text(json.dumps({"size": [w, h], "frames": frames, "seed": seed, "grain": grain,
                                "times": [float(x) for x in bracket.times], "files": [p.name for p in paths]}))
    return paths


_OPENCV_WORKER = r"""
import json, sys, time
t0 = time.perf_counter()
import cv2, numpy as np
from derender.io.exif import read_exposure_time
paths = sys.argv[1:]
times = np.array([read_exposure_time(p) for p in paths], dtype=np.float32)
t1 = time.perf_counter()
imgs = [cv2.imread(p) for p in paths]
t2 = time.perf_counter()
resp = cv2.createCalibrateDebevec().process(imgs, times)
t3 = time.perf_counter()
hdr = cv2.createMergeDebevec().process(imgs, times, resp)
t4 = time.perf_counter()
print(json.dumps({"inner_s": t4 - t1, "decode_s": t2 - t1, "calibrate_s": t3 - t2, "merge_s": t4 - t3,
                  "threads": cv2.getNumThreads(), "finite": bool(np.isfinite(hdr).all())}))
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
    peak = own / 1024.0 if own is not None else usage.ru_maxrss / 1024.0
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


def _bench_one(name: str, paths: list[Path], outdir: Path, python: str) -> dict:
    files = [str(p) for p in paths]
    if name == "opencv":
        cmd = [python, "-c", _OPENCV_WORKER, *files]
    elif name == "colour-hdri":
        cmd = [python, "-c", _COLOUR_HDRI_WORKER, *files]
    elif name.startswith("derender-"):
        method = name[len("derender-"):]
        cmd = [python, "-m", "derender.cli", "merge", *files, "-o", str(outdir / f"{name}-{len(paths)}.exr"),
               "--method", method]
    else:
        raise InputError(f"unknown benchmark entry {name!r}")
    run = _run_measured(cmd)
    detail = _last_json(run["stdout"])
    status = detail.pop("status", "ok" if run["returncode"] == 0 else "error")
    row = {"status": status, "command": " ".join([Path(cmd[0]).name, *cmd[1:2]] if cmd[1] == "-c" else
                                                  [Path(cmd[0]).name, *cmd[1:5], "...", *cmd[-4:]]),
           "wall_s": run["wall_s"], "peak_rss_mb": run["peak_rss_mb"], "cpu_s": run["cpu_s"], **detail}
    if name.startswith("derender-") and run["returncode"] == 0:
        import re

        m = re.search(r"\(([0-9.]+) s;", run["stdout"])
        if m:
            row["inner_s"] = float(m.group(1))
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


def run_bench(size: tuple[int, int] = (6000, 4000), frames: int = 9, workdir: str | os.PathLike | None = None,
              entries: Sequence[str] | None = None, memory_frames: int | None = None, seed: int = 0,
              repeat: int = 1, python: str | None = None, progress: Callable[[str], None] | None = None) -> dict:
    """Side-by-side benchmark on a generated bracket (:func:`generate_bench_bracket`), each run in a fresh process.

    ``entries`` (default all): ``"opencv"`` (cv2.imread x N + CalibrateDebevec +
    MergeDebevec, no file written), ``"colour-hdri"`` (``image_stack_to_HDRI``; skipped
    when not importable), ``"derender-debevec"`` and ``"derender-stabilized"`` (the
    ``derender merge`` command: decode, calibrate, merge and EXR write; stabilized only
    when the method is registered). With ``memory_frames`` (e.g. 18) ``derender merge
    --method debevec`` also runs on a bracket of that many frames, to compare peak RSS.
    Wall time is the whole process (interpreter start included); ``inner_s`` the
    tool's own timing; peak RSS from ``wait4``. ``repeat`` > 1 keeps the fastest run.
    Returns a dict (see :func:`format_bench`).
    """
    python = python or sys.executable
    workdir = Path(workdir) if workdir is not None else Path(tempfile.gettempdir()) / "derender-bench"
    workdir.mkdir(parents=True, exist_ok=True)
    say = progress or (lambda msg: None)
    if entries is None:
        entries = ["opencv", "colour-hdri", "derender-debevec", "derender-stabilized"]
    say(f"generating {frames} frames {size[0]}x{size[1]} in {workdir} (cached)")
    paths = generate_bench_bracket(workdir, size, frames, seed)
    outdir = workdir / "outputs"
    outdir.mkdir(exist_ok=True)
    runs: dict[str, dict] = {}
    for name in entries:
        if name == "derender-stabilized" and not method_registered("stabilized"):
            runs[name] = {"status": "skipped", "reason": "method 'stabilized' is not registered"}
            continue
        best = None
        for _ in range(max(1, int(repeat))):
            say(f"running {name}")
            row = _bench_one(name, paths, outdir, python)
            if row["status"] != "ok":
                best = row
                break
            if best is None or row["wall_s"] < best["wall_s"]:
                best = row
        runs[name] = best
    result: dict[str, Any] = {
        "size": [int(size[0]), int(size[1])], "frames": int(frames), "workdir": str(workdir),
        "input_mb": sum(p.stat().st_size for p in paths) / 1e6,
        "cpus": thread_count(None), "load_avg": list(os.getloadavg()), "runs": runs, "ratios": {},
    }
    ok = {k: v for k, v in runs.items() if v.get("status") == "ok"}
    if "opencv" in ok:
        for k, v in ok.items():
            if k != "opencv":
                result["ratios"][f"{k} / opencv"] = v["wall_s"] / ok["opencv"]["wall_s"]
    if "derender-stabilized" in ok and "derender-debevec" in ok:
        result["ratios"]["derender-stabilized / derender-debevec"] = (ok["derender-stabilized"]["wall_s"]
                                                                      / ok["derender-debevec"]["wall_s"])
    if memory_frames:
        say(f"generating {memory_frames} frames for the memory comparison")
        big = generate_bench_bracket(workdir, size, int(memory_frames), seed)
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
    """Markdown table of a :func:`run_bench` result."""
    w, h = result["size"]
    lines = [f"{result['frames']} JPEGs {w}x{h} ({w * h / 1e6:.1f} MP, {result['input_mb']:.0f} MB), "
             f"{result['cpus']} CPUs, load average {result['load_avg'][0]:.2f}", "",
             "| tool | status | wall s | inner s | peak RSS MB | CPU s | vs OpenCV |",
             "|---|---|---|---|---|---|---|"]
    ocv = result["runs"].get("opencv", {})
    for name, r in result["runs"].items():
        if r.get("status") != "ok":
            lines.append(f"| {name} | {r.get('status')}: {r.get('reason', '')} | | | | | |")
            continue
        ratio = f"{r['wall_s'] / ocv['wall_s']:.2f}x" if ocv.get("status") == "ok" else ""
        inner = f"{r['inner_s']:.2f}" if "inner_s" in r else ""
        lines.append(f"| {name} | ok | {r['wall_s']:.2f} | {inner} | {r['peak_rss_mb']:.0f} | {r['cpu_s']:.1f} | {ratio} |")
    for k, v in result.get("ratios", {}).items():
        lines.append(f"\n{k}: {v:.2f}")
    mem = result.get("memory")
    if mem:
        a, b = mem["frames"]
        ra, rb = mem["peak_rss_mb"]
        txt = f"\nmemory: derender-debevec peak RSS {a} frames {ra:.0f} MB, {b} frames {rb:.0f} MB"
        if "rss_ratio" in mem:
            txt += f" (ratio {mem['rss_ratio']:.2f})"
        lines.append(txt)
    return "\n".join(lines)
