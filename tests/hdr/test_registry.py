"""The method registry (issue 26): one :class:`MethodSpec` per method, one options record per
method shared by its merge function, its engine method and the CLI."""

from __future__ import annotations

import dataclasses
import inspect

import numpy as np
import pytest

from derender.core.errors import InputError
from derender.hdr.registry import METHODS, method_options, method_spec, parse_options


@pytest.mark.parametrize("name", sorted(METHODS))
def test_each_method_lists_its_options_once(name):
    """Every built-in method names a frozen, keyword-only record, the one place its options are
    written: its merge function takes the record (``fn(stack, options, *, motion)``), its engine
    factory and its float-stack merge are made from it."""
    spec = method_spec(name)
    cls = spec.options_class()
    assert dataclasses.is_dataclass(cls) and cls.__dataclass_params__.frozen
    assert all(f.kw_only for f in dataclasses.fields(cls))
    params = list(inspect.signature(spec.load()).parameters)
    assert params[1:] == ["options", "motion"], params
    factory = spec.engine_factory()
    if spec.inputs == "raw":       # the RAW method runs outside the engine for now (its plans read 8-bit codes)
        assert factory is None and spec.files is not None
        return
    assert factory is not None and callable(factory)
    assert callable(spec.stack_function())


def test_a_misspelt_option_names_the_method_and_its_options():
    with pytest.raises(InputError, match=r"'stabilized' does not accept option\(s\) blok; accepted: response,"):
        method_options("stabilized", {"blok": 4})
    with pytest.raises(InputError, match="needs option"):
        method_options("probabilistic", {})


def test_a_text_option_reaches_the_engine_method_through_the_record(monkeypatch):
    """``--option block=4`` is parsed to the record's type, and the engine method is built from
    that record (what ``derender merge`` runs)."""
    from derender.camera import simulate_bracket
    from derender.core.types import Stack
    from derender.hdr.registry import merge
    from derender.hdr.stabilize import method as stab

    record = method_options("stabilized", parse_options("stabilized", ["block=4", "use_times=false"]))
    assert isinstance(record, stab.StabilizedOptions) and record.block == 4 and record.use_times is False
    seen = []
    original = stab.StabilizedMethod.__init__

    def spy(self, name, options):
        seen.append(options)
        original(self, name, options)

    monkeypatch.setattr(stab.StabilizedMethod, "__init__", spy)
    b = simulate_bracket(size=(64, 48), exposures=4, seed=2)
    st = Stack(images=b.jpeg_codes.astype(np.float32) / np.float32(255), times=b.times)
    res = merge(st, options={"block": 4}, method="stabilized")
    assert np.isfinite(res.radiance).all()
    assert seen and seen[-1].block == 4 and seen[-1].use_times is True


def test_no_option_is_accepted_only_to_be_ignored():
    """The probabilistic merge takes no seed (it is deterministic), and the classic engine
    methods read their record instead of absorbing an ``engine`` keyword."""
    assert not method_spec("probabilistic").has_option("seed")
    from derender.hdr.classic import DebevecMethod

    assert list(inspect.signature(DebevecMethod).parameters) == ["options"]
