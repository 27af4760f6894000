"""derender: linear scene radiance, with uncertainty, from rendered 8-bit camera images.

The package's folders are the stages of the pipeline (docs/architecture.md); imports go
down these layers only (checked in CI by ``tests/test_layering.py``)::

    cli
    evaluation | applications        scoring, experiments; photometric stereo
    hdr                              merge methods: classic, paper 1, paper 2; files
    derendering                      p(RAW colour | JPEG colour) models (paper 2)
    response                         Debevec 1997, Robertson 2003
    engine | camera | raw            the merge engine; the simulator; RAW development
    io                               file formats
    core                             types, errors, colorimetry

The most used functions are re-exported here and load on first use.
"""

from __future__ import annotations

from derender.core.lazy import attach

#: The package's version (PEP 440), the one its installed metadata carries.
#:
#: Examples
#: --------
#: >>> import importlib.metadata
#: >>> import derender
#: >>> derender.__version__ == importlib.metadata.version("derender")
#: True
__version__ = "0.1.0"

__getattr__, __dir__, _names = attach(__name__, {
    "core.errors": ["DerenderError", "InputError", "ModelFileError", "StackError"],
    "core.types": ["Stack", "RawFrame", "HDRResult"],
    "io.images": ["read_image", "read_stack", "read_codes"],
    "io.raw": ["read_raw", "read_raw_stack"],
    "io.exr": ["read_exr", "write_exr"],
    "io.rgbe": ["read_hdr", "read_radiance"],
    "io.preview": ["write_png", "write_preview"],
    "camera.bracket": ["simulate_bracket"],
    "raw.groundtruth": ["raw_ground_truth", "raw_to_camera_rgb"],
    "raw.optimal": ["raw_merge"],
    "response.debevec1997": ["calibrate_debevec"],
    "response.robertson2003": ["calibrate_robertson"],
    "engine.float_merge": ["merge_linear"],
    "engine.motion.run": ["MotionOptions"],
    "engine.options": ["OutputOptions", "EngineOptions"],
    "hdr.registry": ["merge", "register_method", "METHODS", "MethodSpec"],
    "hdr.files": ["merge_files"],
    "derendering.base": ["MODEL_TYPES", "DerenderModel", "fit_model", "load_model"],
    "derendering.local_gp": ["LocalGPModel"],
    "derendering.polynomial": ["PolynomialModel"],
    "derendering.rbf": ["RBFModel"],
    "derendering.apply": ["derender_image", "derender_to_exr"],
    "applications.photometric_stereo": ["solve_normals"],
    "evaluation.metrics": ["psnr_rgbl"],
    "evaluation.derendering_metrics": ["relative_rmse", "interval_coverage"],
})
__all__ = ["__version__", *_names]
del _names
