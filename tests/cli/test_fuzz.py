"""Fuzzing the input contract (issue 15, item 9): real files mutated by hypothesis -- truncated,
bytes flipped, headers forged, times shuffled -- through the readers and the CLI.

Whatever the mutation, ``derender merge`` either exits 0 with a finite, non-negative radiance
map, or exits 2 with one ``error:`` line and no traceback; it never leaves a file behind on
failure and never changes an input. Seeds are fixed (``derandomize``) so CI is repeatable.
"""

from __future__ import annotations

import hashlib
import os
import struct
from pathlib import Path

import numpy as np
import pytest
from helpers import run_cli
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from derender.core.errors import InputError
from derender.io.exr import read_exr
from derender.io.headers import probe_image
from derender.io.images import decode_image

#: ``DERENDER_FUZZ_EXAMPLES=N`` runs N examples per test with fresh random seeds (a long hunt);
#: CI runs the fixed, derandomised default.
_LONG = int(os.environ.get("DERENDER_FUZZ_EXAMPLES", "0"))
FUZZ = settings(max_examples=_LONG or 60, deadline=None, derandomize=not _LONG, print_blob=bool(_LONG),
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
FUZZ_CLI = settings(FUZZ, max_examples=_LONG or 30)

#: Methods fuzzed through the CLI (every engine path: tables, Robertson's linear tables, matrices).
METHODS = ["debevec", "robertson", "stabilized"]


def _scene(h=40, w=56):
    y, x = np.mgrid[0:h, 0:w]
    return 0.02 + np.stack([x / w, y / h, 0.5 * (x + y) / (w + h)], -1)


def _encode(codes: np.ndarray, fmt: str) -> bytes:
    import cv2

    ok, enc = cv2.imencode(fmt, np.ascontiguousarray(codes[..., ::-1]))
    assert ok
    return enc.tobytes()


@pytest.fixture(scope="module")
def originals() -> dict:
    """Three valid exposures (times 1, 2, 4) as JPEG and PNG bytes."""
    out = {}
    for fmt in (".jpg", ".png"):
        out[fmt] = [_encode(np.clip(255 * (_scene() * 2.0**j) ** (1 / 2.2), 0, 255).astype(np.uint8), fmt)
                    for j in range(3)]
    return out


def _mutate(data: bytes, kind: str, pos: float, value: int) -> bytes:
    b = bytearray(data)
    i = min(int(pos * len(b)), len(b) - 1)
    if kind == "truncate":
        return bytes(b[: max(i, 1)])
    if kind == "flip":
        for k in range(1 + value % 8):
            j = (i + 97 * k) % len(b)
            b[j] ^= 1 + (value >> 3) % 255
        return bytes(b)
    if kind == "forge":
        big = 1 + value * 977
        if b[:2] == b"\xff\xd8":
            j = b.find(b"\xff\xc0")
            if j > 0:
                b[j + 5:j + 9] = struct.pack(">HH", big % 65536, (big * 7) % 65536)
        else:
            b[16:24] = struct.pack(">II", big, big * 3)
        return bytes(b)
    return bytes(b)


def _digest(paths) -> list[str]:
    return [hashlib.sha256(Path(p).read_bytes()).hexdigest() for p in paths]


@FUZZ
@given(fmt=st.sampled_from([".jpg", ".png"]), which=st.integers(0, 2),
       kind=st.sampled_from(["truncate", "flip", "forge"]), pos=st.floats(0.0, 1.0), value=st.integers(0, 4000))
def test_readers_never_crash(tmp_path, originals, fmt, which, kind, pos, value):
    p = tmp_path / f"m{fmt}"
    p.write_bytes(_mutate(originals[fmt][which], kind, pos, value))
    try:
        info = probe_image(p)
        img = decode_image(p)
    except InputError as exc:
        assert str(exc) and "\n" not in str(exc)
        return
    assert img.shape == (info.height, info.width, 3) and img.dtype in (np.uint8, np.uint16)


@FUZZ_CLI
@given(fmt=st.sampled_from([".jpg", ".png"]), which=st.integers(0, 2),
       kind=st.sampled_from(["truncate", "flip", "forge", "none"]), pos=st.floats(0.0, 1.0),
       value=st.integers(0, 4000), order=st.permutations([0, 1, 2]),
       method=st.sampled_from(METHODS))
def test_merge_contract_under_mutation(tmp_path_factory, capsys, originals, fmt, which, kind, pos, value, order, method):
    d = tmp_path_factory.mktemp("fuzz")
    paths = []
    for j, data in enumerate(originals[fmt]):
        p = d / f"f{j}{fmt}"
        p.write_bytes(_mutate(data, kind, pos, value) if j == which else data)
        paths.append(p)
    before = _digest(paths)
    times = ",".join(str(2.0 ** k) for k in order)    # shuffled: often contradicts the brightness
    out = d / "out"
    out.mkdir()
    code, _, err = run_cli(["merge", *paths, "-o", out / "o.exr", "--times", times, "--method", method,
                            "--preview", out / "p.png"], capsys)
    assert _digest(paths) == before
    assert "Traceback" not in err
    if code == 0:
        rad = read_exr(out / "o.exr")
        assert np.all(np.isfinite(rad)) and rad.min() >= 0
        assert sorted(q.name for q in out.iterdir()) == ["o.exr", "p.png"]
    else:
        assert code == 2, err
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error:"), err
        assert list(out.iterdir()) == []
    OUTCOMES.append(code if code == 0 else lines[0].split(":")[1][:30])


OUTCOMES: list = []


def test_fuzzing_reached_both_outcomes():
    """The mutations are not all refused early (nor all harmless): both exits were seen."""
    if not OUTCOMES:
        pytest.skip("run with test_merge_contract_under_mutation")
    assert 0 in OUTCOMES and any(o != 0 for o in OUTCOMES)
