"""The merge methods by name: registration, dispatch, and the seeded call used by experiments.

Every method is one :class:`MethodSpec` record in :data:`METHODS`: its name, where its merge
function, options record, engine factory and float-stack merge live, what it gives (a
variance, response curves) and the colour space of its radiance. :func:`merge` dispatches an
in-memory :class:`~derender.core.types.Stack` by name, :func:`derender.hdr.files.merge_files`
image files; both hand the method's options record and the
:class:`~derender.engine.motion.run.MotionOptions` to :func:`run_engine`, the one place that
chooses the engine's plain run, its motion run, or (when the engine has no form for the
method, its options or the input: :class:`~derender.engine.frames.NotStreamable`) the
method's merge on the float reference engine. The built-in methods live in :mod:`derender.hdr.classic` (``debevec``, ``robertson``),
:mod:`derender.hdr.stabilize` (``stabilized``, ``stabilized-joint``, paper 1),
:mod:`derender.hdr.probabilistic` (``probabilistic``, paper 2),
:mod:`derender.hdr.stabilized_probabilistic` (``stabilized-probabilistic``, both papers) and
:mod:`derender.hdr.raw` (``raw``: RAW frames, the noise-optimal merge on the mosaic); a
module is imported when its method is first used. A method defined outside the package joins
with the :func:`register_method` decorator.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
from dataclasses import MISSING, dataclass, field, fields, make_dataclass
from typing import Any, Callable, Mapping

from derender.core.errors import InputError
from derender.core.types import HDRResult, Stack
from derender.engine.frames import ArrayFrames, NotStreamable
from derender.engine.motion.run import MotionOptions
from derender.engine.options import EngineOptions, OutputOptions

__all__ = [
    "MethodSpec",
    "METHODS",
    "method_spec",
    "register_method",
    "get_method",
    "method_options",
    "seeded_options",
    "merge",
    "merge_seeded",
    "merge_stack",
    "run_engine",
    "settable_options",
    "parse_options",
]

#: Keywords of merge functions that are not user options: set by their own CLI flags
#: (``model``: ``-m``; ``seed``: ``--seed``; ``variance``: ``--variance``), arrays (``curves``), or the engine choice.
_NOT_SETTABLE = ("model", "seed", "curves", "engine", "variance")


# --------------------------------------------------------------------------- registry
def _resolve(target: Any) -> Any:
    """A ``"package.module:attribute"`` string imported and looked up; anything else as is."""
    if not isinstance(target, str):
        return target
    module, _, attr = target.partition(":")
    return getattr(importlib.import_module(module), attr)


@dataclass(frozen=True)
class MethodSpec:
    """One merge method: what ``derender methods`` prints and what the engine and the CLI read.

    Attributes
    ----------
    name : str
        The method's name (``derender merge --method NAME``).
    function : str or callable
        The method's merge function, or where it lives as ``"package.module:name"`` (imported
        on first use: a Debevec merge does not pay the ~1 s start-up of the stabiliser and the
        de-rendering models): for a built-in method ``fn(stack, options=None, *, motion=None)``
        (``merge(stack, name, options, motion=motion)``: its docstring is what ``derender
        methods`` prints); for a method defined outside the package ``fn(stack, *, option=default, ...)``.
    engine : str or callable or None
        ``factory(options) -> EngineMethod`` (``options``: the method's record), or its
        ``"module:name"``; None for a method that runs only in memory. A factory that has no
        engine form for some options raises :class:`~derender.engine.frames.NotStreamable`.
    options : str or type or None
        The method's options record: a frozen, keyword-only dataclass (or its
        ``"module:name"``), where each option is written once; the engine factory and the
        float-stack merge take it. None (a method defined outside the package): a record is
        made from the function's keywords after the stack.
    stack : str or callable or None
        ``fn(stack, options) -> HDRResult``: the method on the float reference engine, where
        the engine has no form for it (:func:`run_engine` chooses); None: ``function`` called
        with the record's fields as keywords (a method defined outside the package).
    gives_variance, gives_curves : bool
        Its results carry a per-pixel variance (``--variance``) / response curves
        (``result.info["curves"]``, what ``derender merge --plot`` draws).
    output_space : str
        The colour space of its radiance, in words.
    inputs : str
        ``"rendered"`` (a :class:`~derender.core.types.Stack` of 8- or 16-bit images) or
        ``"raw"`` (a list of :class:`~derender.core.types.RawFrame`; files through
        ``files``, a ``"module:name"`` like :func:`derender.hdr.raw.merge_raw_files`).
    files : str or callable or None
        For RAW methods: ``fn(paths, times, options, motion, output, engine, *, inputs) ->
        HDRResult`` (the records of :func:`derender.hdr.files.merge_files`), what
        :func:`~derender.hdr.files.merge_files` calls.

    Examples
    --------
    The records of the built-in methods are in :data:`METHODS`:

    >>> import derender
    >>> spec = derender.METHODS["debevec"]
    >>> spec.name, spec.inputs, spec.gives_variance, spec.gives_curves
    ('debevec', 'rendered', True, True)
    >>> spec.load().__name__, spec.has_option("lam")
    ('merge_debevec', True)
    """

    name: str
    function: Any
    engine: Any = None
    options: Any = None
    stack: Any = None
    gives_variance: bool = False
    gives_curves: bool = False
    output_space: str = "not stated"
    inputs: str = "rendered"
    files: Any = None

    def load(self) -> Callable[..., HDRResult]:
        """The merge function (its module imported on first use)."""
        return _resolve(self.function)

    def files_function(self) -> Callable[..., HDRResult] | None:
        """The merge of files for a RAW method (``files``), or None."""
        return _resolve(self.files)

    def engine_factory(self) -> Callable[[Any], Any] | None:
        """The engine factory (``factory(options_record) -> EngineMethod``), or None."""
        return _resolve(self.engine)

    def stack_function(self) -> Callable[[Stack, Any], HDRResult]:
        """``fn(stack, options_record) -> HDRResult``: the method on the float reference engine
        (``stack``), or its merge function called with the record's fields as keywords."""
        if self.stack is not None:
            return _resolve(self.stack)
        fn = self.load()
        return lambda stack, record: fn(stack, **{f.name: getattr(record, f.name) for f in fields(record)})

    def options_class(self) -> type:
        """The options record's class (made from the merge function's signature when the
        method names none)."""
        if self.options is not None:
            return _resolve(self.options)
        return _signature_record(self.name, self.load())

    @property
    def module(self) -> str:
        """The module that defines the method."""
        if isinstance(self.function, str):
            return self.function.partition(":")[0]
        return getattr(self.function, "__module__", "?")

    def has_option(self, name: str) -> bool:
        """Whether the method's options record has a field ``name``."""
        return name in {f.name for f in fields(self.options_class())}

    @property
    def needs_model(self) -> bool:
        """Whether the method needs a de-rendering model (``-m MODEL.npz``): its record has a
        ``model`` field."""
        return self.has_option("model")

    @property
    def summary(self) -> str:
        """The first sentence of the merge function's docstring, as plain text (no reST markup)."""
        return method_summary(self.load())


_RENDERED = ("linear RGB of the images' own rendering (their primaries and white balance; linear sRGB for "
             "in-camera JPEGs), relative units")
_CLASSIC = "derender.hdr.classic"
_STABILIZED = "derender.hdr.stabilize.method"
_PROBABILISTIC = "derender.hdr.probabilistic"
_BOTH = "derender.hdr.stabilized_probabilistic"
_RAW = "derender.hdr.raw"

#: Every merge method by name. The built-in ones are listed here, one line each, and imported on
#: first use; a method defined elsewhere joins with :func:`register_method`.
#:
#: Examples
#: --------
#: >>> import derender
#: >>> sorted(derender.METHODS)  # doctest: +NORMALIZE_WHITESPACE
#: ['debevec', 'probabilistic', 'raw', 'robertson', 'stabilized', 'stabilized-joint',
#:  'stabilized-probabilistic']
#: >>> derender.METHODS["raw"].inputs
#: 'raw'
METHODS: dict[str, MethodSpec] = {spec.name: spec for spec in (
    MethodSpec("debevec", f"{_CLASSIC}:merge_debevec", f"{_CLASSIC}:DebevecMethod", f"{_CLASSIC}:DebevecOptions",
               f"{_CLASSIC}:debevec_stack", gives_variance=True, gives_curves=True, output_space=_RENDERED),
    MethodSpec("robertson", f"{_CLASSIC}:merge_robertson", f"{_CLASSIC}:RobertsonMethod",
               f"{_CLASSIC}:RobertsonOptions", f"{_CLASSIC}:robertson_stack", gives_variance=True, gives_curves=True,
               output_space=_RENDERED),
    MethodSpec("stabilized", f"{_STABILIZED}:merge_stabilized", f"{_STABILIZED}:stabilized_engine",
               f"{_STABILIZED}:StabilizedOptions", f"{_STABILIZED}:stabilized_stack", gives_variance=True,
               output_space=_RENDERED + ", in the reference frame's white balance"),
    MethodSpec("stabilized-joint", f"{_STABILIZED}:merge_stabilized_joint", f"{_STABILIZED}:stabilized_joint_engine",
               f"{_STABILIZED}:StabilizedOptions", f"{_STABILIZED}:stabilized_joint_stack", gives_variance=True,
               output_space=_RENDERED + ", in the bracket's average rendering"),
    MethodSpec("probabilistic", f"{_PROBABILISTIC}:merge_probabilistic", f"{_PROBABILISTIC}:probabilistic_engine",
               f"{_PROBABILISTIC}:ProbabilisticOptions", f"{_PROBABILISTIC}:probabilistic_stack", gives_variance=True,
               output_space=("linear sRGB: the model's camera RGB through its camera-to-sRGB matrix (option "
                             "colour_space='camera_rgb' keeps camera RGB); scaled to exposure time 1 s")),
    MethodSpec("stabilized-probabilistic", f"{_BOTH}:merge_stabilized_probabilistic",
               f"{_BOTH}:StabilizedProbabilisticMethod", f"{_BOTH}:StabilizedProbabilisticOptions",
               f"{_BOTH}:stabilized_probabilistic_stack", gives_variance=True,
               output_space=_RENDERED + ", in the reference frame's white balance"),
    MethodSpec("raw", f"{_RAW}:merge_raw", None, f"{_RAW}:RawOptions", gives_variance=True,
               output_space=("linear sRGB through the files' own colour matrix and as-shot white balance (option "
                             "output_space: camera_rgb, xyz); white level per second"),
               inputs="raw", files=f"{_RAW}:merge_raw_files"),
)}


def register_method(name: str, *, gives_variance: bool = False, engine: Callable[[Any], Any] | None = None,
                    options: type | None = None, gives_curves: bool = False,
                    output_space: str | None = None) -> Callable[[Callable[..., HDRResult]], Callable[..., HDRResult]]:
    """Decorator adding ``fn(stack, *, option=default, ...) -> HDRResult`` to :data:`METHODS`
    as ``name`` (a method defined outside the package; the fields are those of
    :class:`MethodSpec`).

    The method's options are its keywords after the stack (its record is made from them);
    :func:`merge` refuses others and calls ``fn`` with the record's fields.

    Parameters
    ----------
    name : str
        The method's name (replaces a method of that name).
    gives_variance : bool
        Its results carry a per-pixel variance.
    engine : callable, optional
        ``factory(options) -> EngineMethod``, its form on the merge engine (None: it runs in
        memory only).
    options : type, optional
        Its options record (a frozen keyword-only dataclass); None: made from ``fn``'s signature.
    gives_curves : bool
        Its results carry response curves in ``info["curves"]``.
    output_space : str, optional
        The colour space of its radiance, in words.

    Returns
    -------
    callable
        The decorator; it registers ``fn`` and returns it unchanged.

    Examples
    --------
    A toy method: undo a gamma, divide by the time, average the frames.

    >>> import numpy as np
    >>> import derender
    >>> radiance = np.geomspace(0.01, 1.0, 16 * 16).reshape(16, 16, 1).repeat(3, axis=2)   # 100:1
    >>> times = np.array([0.25, 1.0, 4.0])
    >>> codes = np.round(255 * np.clip(radiance * times[:, None, None, None], 0, 1) ** (1 / 2.2))
    >>> stack = derender.Stack((codes / 255).astype(np.float32), times)
    >>> @derender.register_method("mean-linear", output_space="linear RGB of the rendering")
    ... def mean_linear(stack, gamma=2.2):
    ...     linear = stack.images ** gamma / stack.times[:, None, None, None]
    ...     return derender.HDRResult(radiance=linear.mean(axis=0).astype(np.float32),
    ...                               mask=np.zeros(stack.shape, np.uint8))
    >>> result = derender.merge(stack, "mean-linear", {"gamma": 2.2})
    >>> result.radiance.shape, derender.METHODS["mean-linear"].gives_variance
    ((16, 16, 3), False)
    >>> try:
    ...     derender.merge(stack, "mean-linear", {"gama": 2.0})
    ... except derender.InputError as error:
    ...     print(error)
    merge method 'mean-linear' does not accept option(s) gama; accepted: gamma
    >>> del derender.METHODS["mean-linear"]   # unregister
    """

    def deco(fn: Callable[..., HDRResult]) -> Callable[..., HDRResult]:
        METHODS[name] = MethodSpec(name, fn, engine, options, gives_variance=bool(gives_variance),
                                   gives_curves=bool(gives_curves), output_space=output_space or "not stated")
        return fn

    return deco


_RECORDS: dict[tuple[str, int], type] = {}


def _signature_record(name: str, fn: Callable[..., HDRResult]) -> type:
    """A frozen, keyword-only dataclass of ``fn``'s keywords (after the stack), for a method that
    names no options record (cached per function)."""
    key = (name, id(fn))
    cls = _RECORDS.get(key)
    if cls is None:
        specs = []
        for k, p in list(inspect.signature(fn).parameters.items())[1:]:
            if p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD):
                continue
            ann = Any if p.annotation is inspect.Parameter.empty else p.annotation
            specs.append((k, ann) if p.default is inspect.Parameter.empty else (k, ann, field(default=p.default)))
        cls = make_dataclass(f"{name.title().replace('-', '')}Options", specs, frozen=True, kw_only=True)
        cls.__module__ = getattr(fn, "__module__", __name__)
        _RECORDS[key] = cls
    return cls


def method_summary(fn: Callable[..., HDRResult]) -> str:
    """The first sentence of a merge function's docstring, as plain text (no reST markup)."""
    import re

    doc = inspect.getdoc(fn) or ""
    para = " ".join(doc.split("\n\n", 1)[0].split())
    m = re.search(r"(?<=[.;])\s+(?=[A-Z(`])", para)
    first = para[:m.start()] if m else para
    first = re.sub(r":\w+:`~?([^`]+)`", lambda g: g.group(1).rsplit(".", 1)[-1], first)
    return first.replace("``", "")


def method_spec(method: str) -> MethodSpec:
    """The :class:`MethodSpec` registered as ``method``; an :class:`InputError` lists the known ones."""
    spec = METHODS.get(method)
    if spec is None:
        from derender.core.options import did_you_mean

        raise InputError(f"unknown merge method {method!r}{did_you_mean(method, METHODS)}; known: "
                         f"{', '.join(sorted(METHODS))}")
    return spec


def get_method(method: str) -> Callable[..., HDRResult]:
    """The merge function registered as ``method``; an :class:`InputError` lists the known ones."""
    return method_spec(method).load()


def method_options(method: str, options: Any = None) -> Any:
    """The options record of merge ``method`` (:meth:`MethodSpec.options_class`): ``options``
    itself when it is one, else made from a mapping of its fields (None: every default), each
    value checked by the record. An unknown option is an :class:`InputError` naming the method
    and listing its options; so is a missing required one."""
    cls = method_spec(method).options_class()
    if isinstance(options, cls):
        return options
    if options is None:
        options = {}
    if not isinstance(options, Mapping):
        raise InputError(f"the options of merge method {method!r} are a {cls.__name__} or a mapping of its fields, "
                         f"got {type(options).__name__}")
    names = [f.name for f in fields(cls)]
    bad = [k for k in options if k not in names]
    if bad:
        raise InputError(f"merge method {method!r} does not accept option(s) {', '.join(bad)}; "
                         f"accepted: {', '.join(names)}")
    missing = [f.name for f in fields(cls)
               if f.default is MISSING and f.default_factory is MISSING and f.name not in options]
    if missing:
        raise InputError(_missing_message(method, missing))
    return cls(**options)


def seeded_options(method: str, seed: int, options: Any = None) -> Any:
    """The options record of ``method`` (:func:`method_options`) with ``seed`` when the method
    takes one (the others are deterministic, or seeded by nothing the caller gives)."""
    record = method_options(method, options)
    if method_spec(method).has_option("seed"):
        record = dataclasses.replace(record, seed=int(seed))
    return record


def _missing_message(method: str, missing: list[str]) -> str:
    hint = " (-m MODEL.npz)" if missing == ["model"] else ""
    return f"merge method {method!r} needs option(s) {', '.join(missing)}{hint}"


def _engine_choice(record: Any) -> str:
    """The record's ``engine`` option (``"auto"``, ``"table"``, ``"reference"``; the classic
    methods have one), else ``"auto"``."""
    return getattr(record, "engine", "auto")


def _engine_method(spec: MethodSpec, record: Any) -> tuple[Any, str | None]:
    """The method's :class:`~derender.engine.plans.EngineMethod` for ``record``, or None and why
    (no engine form, ``engine="reference"`` asked for, or its factory's
    :class:`~derender.engine.frames.NotStreamable`)."""
    factory = spec.engine_factory()
    if factory is None:
        return None, "it runs outside the engine"
    if _engine_choice(record) == "reference":
        return None, "engine='reference' asked for"
    try:
        return factory(record), None
    except NotStreamable as exc:
        return None, str(exc)


def run_engine(spec: MethodSpec, record: Any, motion: MotionOptions | None, source: Any,
               output: OutputOptions | None = None, engine: EngineOptions | None = None, *,
               inputs: Any = (), order_hint: str | None = None) -> HDRResult | None:
    """Merge ``source`` (:class:`~derender.engine.frames.FileFrames` or
    :class:`~derender.engine.frames.ArrayFrames`; None: the input has no 8-bit codes) with
    method ``spec`` and its options ``record`` on the engine: the motion run
    (:func:`derender.engine.motion.run.run_motion`) when ``motion`` asks for more than the
    method's own registration (:meth:`~derender.engine.motion.run.MotionOptions.needs_motion_run`),
    else the plain run (:func:`derender.engine.run.run`).

    The one place that decides between the engine and the float reference engine: returns
    None when the engine has no form for the method, its options or the input
    (:class:`~derender.engine.frames.NotStreamable`), and the caller then merges the stack with
    :func:`merge_stack`. Reference frame, alignment and ghost removal need the engine: without
    it they are an :class:`InputError`."""
    from derender.engine.motion.run import run_motion
    from derender.engine.run import run

    method, why = _engine_method(spec, record)
    if motion is not None and motion.needs_motion_run(getattr(method, "own_align", "none")):
        if method is None:
            raise InputError(f"merge method {spec.name!r} with these options runs outside the engine ({why}): "
                             "reference, align and deghost need the engine")
        if source is None:
            raise InputError("alignment and ghost removal need 8-bit images (every value a code / 255)")
        try:
            return run_motion(method, source, motion, output, engine, inputs=inputs, order_hint=order_hint)
        except NotStreamable as exc:
            raise InputError(f"merge method {spec.name!r} cannot align or remove ghosts on these images ({exc})") from None
    if method is None:
        return None
    try:
        if source is None:
            raise NotStreamable("the stack's values are not 8-bit codes")
        return run(method, source, output, engine, inputs=inputs, order_hint=order_hint)
    except NotStreamable as exc:
        if _engine_choice(record) == "table":
            raise InputError(f"engine='table' needs 8-bit images (every value a code / 255): {exc}") from None
        return None


def merge_stack(spec: MethodSpec, stack: Stack, record: Any) -> HDRResult:
    """Method ``spec`` with its options ``record`` on an in-memory ``stack`` through the float
    reference engine (:meth:`MethodSpec.stack_function`): what :func:`run_engine` leaves to
    the caller. ``info["engine_path"]`` is ``"stack"``."""
    res = spec.stack_function()(stack, record)
    res.info["engine_path"] = "stack"
    return res


def _motion(motion: Any) -> MotionOptions | None:
    if motion is not None and not isinstance(motion, MotionOptions):
        raise InputError(f"motion must be a MotionOptions, got {type(motion).__name__}")
    return motion


def merge(stack: Stack, method: str = "debevec", options: Any = None, *,
          motion: MotionOptions | None = None) -> HDRResult:
    """Merge a :class:`~derender.core.types.Stack` into an HDR radiance map with a registered method.

    Parameters
    ----------
    stack : Stack
        The bracket: 8- or 16-bit images as float32 ``(N, H, W, 3)`` in [0, 1] and their
        exposure times (:func:`derender.io.images.read_stack` makes one from files); for a
        method on RAW frames (``raw``), a list of :class:`~derender.core.types.RawFrame`
        (:func:`derender.io.raw.read_raw_stack`).
    method : str
        A name of :data:`METHODS` (``derender methods`` lists them with their options).
    options : options record or mapping, optional
        The method's options: its record (:meth:`MethodSpec.options_class`, e.g.
        :class:`~derender.hdr.classic.DebevecOptions`), or a mapping of the record's fields
        (for text values, :func:`parse_options`), checked once into the record; None: the
        defaults. Paper 2's methods need ``model`` (a
        :class:`~derender.derendering.base.DerenderModel` or a path).
    motion : MotionOptions, optional
        The engine's reference frame, alignment and ghost removal, for every method
        (:class:`~derender.engine.motion.run.MotionOptions`: ``reference`` an index among the
        images, from 0, or ``"auto"``; ``align`` ``"none"``, ``"translation"`` or
        ``"homography"``; ``deghost``, ``ghost_threshold``, ``compensate``, ``consensus``);
        paper 1's methods register to their own reference by translation without it.

    Returns
    -------
    HDRResult
        ``radiance`` (H, W, 3) float32, finite and non-negative; ``mask`` (0 merged, 1 taken
        from the shortest exposure, 2 from the longest); ``variance`` for the methods that give
        one; ``info`` (the method's parameters, timings, ``n_clipped``; with the engine's
        options also ``reference``, ``alignment``, ``deghost``); ``ghosts`` (how many frames
        were left out per pixel) when the engine aligned or removed ghosts.

    Raises
    ------
    InputError
        An unknown method or option (the message lists the known ones), a missing required
        option, or input the method cannot merge.

    References
    ----------
    The methods' papers are cited in their modules: Debevec & Malik 1997
    (:mod:`derender.response.debevec1997`), Robertson et al. 2003
    (:mod:`derender.response.robertson2003`), paper 1 (:mod:`derender.hdr.stabilize`) and
    paper 2 (:mod:`derender.hdr.probabilistic`).

    Examples
    --------
    Three exposures, two stops apart, of a 100:1 ramp through a gamma-2.2 camera; Debevec's
    method recovers the response from the images and the ramp's range within 2 %:

    >>> import numpy as np
    >>> import derender
    >>> radiance = np.geomspace(0.01, 1.0, 16 * 16).reshape(16, 16, 1).repeat(3, axis=2)   # 100:1
    >>> times = np.array([0.25, 1.0, 4.0])
    >>> codes = np.round(255 * np.clip(radiance * times[:, None, None, None], 0, 1) ** (1 / 2.2))
    >>> stack = derender.Stack((codes / 255).astype(np.float32), times)
    >>> result = derender.merge(stack, "debevec")
    >>> result.radiance.shape, result.radiance.dtype, int(result.mask.max())
    ((16, 16, 3), dtype('float32'), 0)
    >>> contrast = result.radiance[15, 15, 1] / result.radiance[0, 0, 1]
    >>> bool(abs(contrast / 100 - 1) < 0.02)
    True

    The method's options as a mapping (or its record), the engine's motion options as a
    :class:`~derender.engine.motion.run.MotionOptions`: here the middle frame as the reference
    and ghost removal (nothing moves, so no frame is left out):

    >>> hat = derender.merge(stack, "debevec", {"weight": "hat"})
    >>> still = derender.merge(stack, "debevec", motion=derender.MotionOptions(reference=1, deghost=True))
    >>> still.info["reference"], int(still.ghosts.max())
    (1, 0)
    >>> try:
    ...     derender.merge(stack, "no-such-method")
    ... except derender.InputError as error:
    ...     print(str(error).split(";")[0])
    unknown merge method 'no-such-method'
    """
    spec = method_spec(method)
    record = method_options(method, options)   # unknown, missing or bad options: one error before any work
    motion = _motion(motion)
    if spec.inputs == "raw":
        return spec.load()(stack, record, motion=motion)
    if not isinstance(stack, Stack):
        raise InputError(f"merge() needs a Stack, got {type(stack).__name__}")
    from derender.engine.tables import stack_codes_exact

    codes = None if stack.bit_depth == 16 else stack_codes_exact(stack.images)
    res = run_engine(spec, record, motion, None if codes is None else ArrayFrames(codes, stack.times))
    return res if res is not None else merge_stack(spec, stack, record)


def merge_seeded(stack: Stack, method: str, seed: int = 0, options: Any = None, *,
                 motion: MotionOptions | None = None) -> HDRResult:
    """:func:`merge`, with ``seed`` in the options of methods that take one
    (:func:`seeded_options`) and in ``motion`` (the homography's RANSAC)."""
    if motion is not None:
        motion = dataclasses.replace(_motion(motion), seed=int(seed))
    return merge(stack, method, seeded_options(method, seed, options), motion=motion)


# --------------------------------------------------------------------------- options from text
def settable_options(method: str) -> dict[str, tuple[Any, Any]]:
    """The options of ``method`` a user can set as text (``derender merge --option NAME=VALUE``):
    ``{name: (type, default)}``, the type from the options record's field."""
    cls = method_spec(method).options_class()
    out = {}
    for f in fields(cls):
        if f.name in _NOT_SETTABLE or f.type is Any or f.default is MISSING:
            continue
        tp = _annotation(cls, f.type)
        if tp is not None and tp is not Any:
            out[f.name] = (tp, f.default)
    return out


def _annotation(cls: type, ann: Any) -> Any:
    """A field's annotation as a type (string annotations evaluated in the record's module;
    None when that fails)."""
    import sys
    import typing

    if not isinstance(ann, str):
        return ann
    module = sys.modules.get(cls.__module__)
    try:
        return eval(ann, {**vars(typing), **(vars(module) if module else {})})  # noqa: S307 - our own annotations
    except Exception:  # noqa: BLE001
        return None


def _type_name(tp: Any) -> str:
    import typing

    args = [a for a in typing.get_args(tp) if a is not type(None)]
    if typing.get_origin(tp) in (typing.Union, getattr(__import__("types"), "UnionType", None)) and args:
        return " or ".join(_type_name(a) for a in args) + " or none"
    if typing.get_origin(tp) is not None and args:
        return f"list of {_type_name(args[0])}"
    return getattr(tp, "__name__", str(tp))


def _parse_value(text: str, tp: Any, name: str, method: str) -> Any:
    import collections.abc
    import typing

    args = [a for a in typing.get_args(tp) if a is not type(None)]
    optional = type(None) in typing.get_args(tp)
    if optional and text.strip().lower() in ("none", ""):
        return None
    if optional and len(args) == 1:
        tp = args[0]
    origin = typing.get_origin(tp)
    if origin in (list, tuple, collections.abc.Sequence):
        inner = typing.get_args(tp)[0] if typing.get_args(tp) else str
        return [_parse_value(part, inner, name, method) for part in text.split(",") if part.strip()]
    try:
        if tp is bool:
            low = text.strip().lower()
            if low in ("1", "true", "yes", "on"):
                return True
            if low in ("0", "false", "no", "off"):
                return False
            raise ValueError
        if tp in (int, float, str):
            return tp(text.strip())
    except ValueError:
        raise InputError(f"option {name} of method {method!r} takes {_type_name(tp)}, got {text!r}") from None
    raise InputError(f"option {name} of method {method!r} cannot be given as text")


def parse_options(method: str, items: list[str] | tuple[str, ...]) -> dict[str, Any]:
    """``["NAME=VALUE", ...]`` as the keyword options of ``method``, each value converted to
    the option's type (``true``/``false`` for flags, ``none`` for an optional value, commas for
    lists). A misspelt or unknown name is an :class:`InputError` listing the valid ones."""
    valid = settable_options(method)
    out: dict[str, Any] = {}
    for item in items:
        name, sep, value = item.partition("=")
        name = name.strip().replace("-", "_")
        if not sep or not name:
            raise InputError(f"--option takes NAME=VALUE, got {item!r}")
        if name not in valid:
            from derender.core.options import did_you_mean

            listing = ", ".join(f"{k} ({_type_name(t)}, default {d!r})" for k, (t, d) in valid.items()) or "none"
            raise InputError(f"method {method!r} has no option {name!r}{did_you_mean(name, valid)}; its options: "
                             f"{listing}")
        if name in out:
            raise InputError(f"option {name} given twice")
        out[name] = _parse_value(value, valid[name][0], name, method)
    return out
