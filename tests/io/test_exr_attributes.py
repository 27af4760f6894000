"""EXR header attributes: our reader against the OpenEXR package, and a reserved attribute
filled in place after the pixels are written (a merge's summary record)."""

from __future__ import annotations

import numpy as np
import pytest

from derender.core.errors import InputError
from derender.io.exr import (
    colour_attributes,
    fill_exr_attribute,
    read_exr,
    read_exr_attributes,
    reserved_text,
    write_exr_fast,
)


def _openexr_header(path) -> dict:
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        return dict(f.header())


def test_attributes_read_as_openexr_reads_them_and_a_reserved_one_fills_in_place(tmp_path):
    img = np.random.default_rng(0).random((37, 53, 3)).astype(np.float32)
    path = tmp_path / "m.exr"
    attrs = {**colour_attributes("linear_srgb", 179.0), "derender:photometry": "absolute: factor 2",
             "derender:summary": reserved_text(256)}
    write_exr_fast(path, img, attributes=attrs)
    ours, peer = read_exr_attributes(path), _openexr_header(path)
    assert ours["whiteLuminance"] == pytest.approx(peer["whiteLuminance"]) == 179.0
    assert ours["derender:photometry"] == peer["derender:photometry"] == "absolute: factor 2"
    assert ours["derender:summary"] == " " * 256
    size = path.stat().st_size
    assert fill_exr_attribute(path, "derender:summary", '{"method":"debevec"}')
    assert not fill_exr_attribute(path, "derender:summary", "x" * 257)         # does not fit: unchanged
    assert not fill_exr_attribute(path, "derender:none", "x")
    peer = _openexr_header(path)
    assert peer["derender:summary"].strip() == '{"method":"debevec"}' == read_exr_attributes(path)["derender:summary"].strip()
    assert path.stat().st_size == size
    np.testing.assert_array_equal(read_exr(path), img)                         # the pixels did not move


def test_a_file_that_is_not_an_exr_is_refused(tmp_path):
    (tmp_path / "x.exr").write_bytes(b"not an exr at all")
    with pytest.raises(InputError, match="not an OpenEXR file"):
        read_exr_attributes(tmp_path / "x.exr")
