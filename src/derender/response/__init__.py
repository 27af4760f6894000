"""Camera response curves: Debevec & Malik (1997) and Robertson et al. (2003), one file per published method.

Modules: :mod:`derender.response.curves`, :mod:`derender.response.debevec1997`, :mod:`derender.response.robertson2003`.
"""

from derender.core.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "curves": ["histogram_samples", "check_usable_histograms", "check_usable_samples", "DEFAULT_LAMBDA", "DEFAULT_SAMPLES", "CHANNELS", "ResponseCurves", "to_codes", "stack_codes", "check_usable", "raise_unusable", "grid_positions", "CLUSTER_REACH", "cluster_positions", "uniform_samples", "sample_pixels", "level_weights", "isotonic_increasing", "make_monotonic", "isotonic_weighted", "smooth_log_curve", "log_slope", "neutral_offsets", "balance_channels", "DEFAULT_TIE", "tie_matrix", "solve_tied", "solve_symmetric", "as_stack", "plot_response"],
    "debevec1997": ["calibrate_debevec_from_samples", "bootstrap_curve_sd", "bracket_curve_sd", "BOOTSTRAP_REPLICATES", "solve_debevec", "solve_debevec_tied", "debevec_system", "solve_dense", "calibrate_debevec", "censored_observations", "white_codes", "CENSOR_RESIDUAL", "CENSOR_ROUNDS", "CENSOR_SPREAD"],
    "robertson2003": ["calibrate_robertson", "robertson_positions", "robertson_clusters", "robertson_from_samples", "calibration_bounds", "noise_weights", "ROBERTSON_LAMBDA", "RIM_CODES"],
})
