"""derender: linear scene radiance, with uncertainty, from rendered 8-bit camera images.

The library is organised as one module per pipeline stage (see ``DESIGN.md``):
``io`` (files), ``camera`` (spectral camera simulator), ``response`` (camera response
curves), ``merge`` (HDR merge engine), ``groundtruth`` (RAW ground truth),
``evaluate`` (PSNR protocol), ``derendering`` (probabilistic de-rendering models).
"""

from __future__ import annotations

__version__ = "0.1.0"

from .errors import DerenderError, InputError, ModelFileError, StackError
from .io import (
    read_exr,
    read_hdr,
    read_image,
    read_radiance,
    read_raw,
    read_raw_stack,
    read_stack,
    write_exr,
    write_png,
    write_preview,
)
from .stack import HDRResult, RawFrame, Stack
from .merge import merge, merge_linear, register_method  # noqa: E402  (the function shadows the module name;
from .evaluate import psnr_rgbl  # noqa: E402             use importlib / "from derender.merge import" for the module)


# de-rendering models load on first use: a CLI command that only merges does not pay for them
_DERENDERING = ("MODEL_TYPES", "DerenderModel", "LocalGPModel", "PolynomialModel", "RBFModel", "fit_model",
                "interval_coverage", "load_model", "relative_rmse")


def __getattr__(name: str):
    """Lazy access to the heavier stage functions (keeps ``import derender`` fast)."""
    lazy = {name: ("derender.derendering", name) for name in _DERENDERING}
    lazy.update({
        "raw_ground_truth": ("derender.groundtruth", "raw_ground_truth"),
        "simulate_bracket": ("derender.camera", "simulate_bracket"),
        "calibrate_debevec": ("derender.response", "calibrate_debevec"),
    })
    if name in lazy:
        import importlib

        mod, attr = lazy[name]
        return getattr(importlib.import_module(mod), attr)
    raise AttributeError(f"module 'derender' has no attribute {name!r}")

__all__ = [
    "__version__",
    "DerenderError",
    "InputError",
    "ModelFileError",
    "StackError",
    "Stack",
    "RawFrame",
    "HDRResult",
    "merge",
    "merge_linear",
    "register_method",
    "psnr_rgbl",
    "MODEL_TYPES",
    "DerenderModel",
    "LocalGPModel",
    "PolynomialModel",
    "RBFModel",
    "fit_model",
    "interval_coverage",
    "load_model",
    "relative_rmse",
    "read_exr",
    "read_hdr",
    "read_image",
    "read_radiance",
    "read_raw",
    "read_raw_stack",
    "read_stack",
    "write_exr",
    "write_png",
    "write_preview",
]
