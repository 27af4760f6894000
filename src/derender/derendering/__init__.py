"""Probabilistic de-rendering (paper 2): p(RAW colour | JPEG colour), one module per method; applying it to images.

Modules: :mod:`derender.derendering.apply`, :mod:`derender.derendering.base`, :mod:`derender.derendering.calibration`, :mod:`derender.derendering.heteroscedastic_gp`, :mod:`derender.derendering.library`, :mod:`derender.derendering.local_gp`, :mod:`derender.derendering.log_space`, :mod:`derender.derendering.model_selection` (``calibrate --method auto``), :mod:`derender.derendering.polynomial`, :mod:`derender.derendering.rbf`.
"""

from derender.core.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "apply": ["check_8bit_rgb", "derender_image", "pack_codes", "ColourIndex", "ColourIndexBuilder", "index_colours", "derender_to_exr"],
    "base": ["model_camera_to_srgb", "MODEL_FORMAT", "MODEL_FORMAT_VERSION", "check_pairs", "as_colour_array", "DerenderModel", "finite32", "load_model", "ModelTypes", "MODEL_TYPES", "model_metadata", "fit_model"],
    "calibration": ["pairs_from_images"],
    "heteroscedastic_gp": ["se_kernel", "noise_gp_weights", "fit_channel"],
    "library": ["resolve_model"],
    "local_gp": ["LocalGPModel"],
    "log_space": ["MAX_LOG_VAR", "MAX_LOG_MEAN", "srgb_decode64", "estimate_raw_white", "log_training_targets", "lognormal_moments", "lognormal_moments_inplace", "table_nodes", "LatentTable"],
    "model_selection": ["pair_arrays", "relative_rmse", "interval_coverage", "SELECTION_METHODS", "DEFAULT_FOLDS", "DEFAULT_CV_TRAIN", "MIN_FOLD_TEST", "MIN_FOLD_TRAIN", "IMAGE_TRUTH_FLOOR", "SELECTION_RULE", "cv_folds", "ModelSelection", "select_model", "fit_calibration", "fit_auto"],
    "polynomial": ["PolynomialModel"],
    "rbf": ["RBFModel"],
})
