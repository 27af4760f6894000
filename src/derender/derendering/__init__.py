"""Probabilistic de-rendering (paper 2): p(RAW colour | JPEG colour) models and applying them to files.

Modules: :mod:`derender.derendering.apply`, :mod:`derender.derendering.models`.
"""

from derender.core.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "apply": ["check_8bit_rgb", "pairs_from_images", "resolve_model", "derender_image", "pack_codes", "ColourIndex", "ColourIndexBuilder", "index_colours", "derender_to_exr"],
    "models": ["model_camera_to_srgb", "MODEL_FORMAT", "MODEL_FORMAT_VERSION", "table_nodes", "DerenderModel", "finite32", "load_model", "LocalGPModel", "PolynomialModel", "RBFModel", "MODEL_TYPES", "model_metadata", "fit_model", "relative_rmse", "rmse", "median_relative_error", "code_floor_errors", "interval_coverage"],
})
