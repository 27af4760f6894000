"""Scoring: the PSNR protocol, paper 1 Table 1 on datasets (Dask), paper 2 experiments, response diagnostics.

Modules: :mod:`derender.evaluation.derendering_metrics`, :mod:`derender.evaluation.diagnose`, :mod:`derender.evaluation.experiments`,
:mod:`derender.evaluation.derendering_families` (paper 2's de-rendering models on every camera-pipeline family),
:mod:`derender.evaluation.families` (every HDR method on every camera-pipeline family), :mod:`derender.evaluation.metrics`,
:mod:`derender.evaluation.neutral` (do greys stay grey at every brightness), :mod:`derender.evaluation.oracle` (merge by
inverting the simulator's true pipeline), :mod:`derender.evaluation.table1`, :mod:`derender.evaluation.uncertainty`
(coverage of a variance against the truth), :mod:`derender.evaluation.ghosts` (moving brackets by zone),
:mod:`derender.evaluation.linearity` (absolute luminance over 5 decades, evalglare's fisheye maps), :mod:`derender.evaluation.raw_merge` (RAW merges
against the simulator's exact truth), :mod:`derender.evaluation.raw_jpeg` (a RAW+JPEG bracket: the JPEG merge
scored against the RAW merge, paper 1's protocol for one's own camera), :mod:`derender.evaluation.consistency` (checks without truth on real brackets:
a still scene with and without ``--deghost``, methods against each other, fidelity to the reference),
:mod:`derender.evaluation.roundtrip` (a merge rendered back through its method's model),
:mod:`derender.evaluation.rendering_change` (can a bracket's frames share one rendering: a test on their codes),
:mod:`derender.evaluation.gallery` (the real brackets' gallery of the documentation).
"""

from derender.core.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "diagnose": ["DiagnoseResult", "diagnose_constant_response", "plot_diagnose"],
    "experiments": ["JPEG_INTERVALS", "METHODS", "default_experiment_cameras", "derender_table", "format_table", "threshold_sweep", "plot_threshold_sweep", "photometric_stereo_experiment"],
    "metrics": ["PSNR_CAP", "fit_scale", "remap_minmax", "psnr", "psnr_rgbl", "fit_colour_matrix", "relative_errors", "log_psnr", "hdr_scores"],
    "table1": ["DEFAULT_DATASET_CAMERAS", "PLANES", "default_methods", "resolve_cameras", "simulate_dataset", "list_scenes", "evaluate_scene", "BenchmarkResult", "run_benchmark", "write_benchmark_outputs", "fusion_gain"],
    "derendering_metrics": ["relative_rmse", "max_colour_share", "rmse", "median_relative_error", "code_floor_errors", "interval_coverage", "fit_and_predict"],
    "derendering_families": ["HELDOUT_ILLUMINANTS", "SPLITS", "derender_families"],
    "demo": ["run_demo", "MODEL_METHODS", "DEMO_TRAIN_PAIRS"],
    "ghosts": ["GHOST_METHODS", "GHOST_SETTINGS", "zone_errors", "ghost_comparison", "summarise_ghosts"],
    "uncertainty": ["COVERAGE_LEVELS", "coverage_scores", "coverage_table", "uncertainty_experiment"],
    "oracle": ["oracle_merge", "oracle_merge_bracket"],
    "raw_merge": ["bracket_raw_frames", "true_noise", "demosaiced_truth", "raw_scores"],
    "raw_jpeg": ["TIME_TOLERANCE", "RawJpegScore", "split_raw_rendered", "pair_raw_jpeg", "score_raw_jpeg"],
    "neutral": ["NeutralAxis", "neutral_pixels", "neutral_axis", "neutral_axis_truth", "scale_gap"],
    "linearity": ["DECADES", "LINEARITY_METHODS", "FISHEYE_VIEW", "linearity_scores", "linearity_experiment", "fisheye_maps", "render_chart_model", "format_decades"],
    "consistency": ["BLOCK", "DARK_QUANTILE", "MapChange", "block_medians", "compare_maps", "STILL_BRACKETS", "FLAG_METHODS", "shared_data_root", "bracket_inputs", "deghost_pair", "flag_invariance", "method_agreement", "reference_fidelity", "FIDELITY_LOW", "FIDELITY_HIGH", "FIDELITY_FLAT", "NEUTRAL_CODES", "NEUTRAL_RATIO", "STEP_REACH", "STEP_HARD", "reference_steps"],
    "gallery": ["GALLERY", "THUMB_WIDTH", "build_gallery", "source_key"],
    "rendering_change": ["IMF_CODES", "IMF_HALF_WIDTH", "IMF_MIN_BLOCKS", "IMF_LOW", "IMF_HIGH", "VIOLATION_CODES",
                         "VIOLATION_FRACTION", "RATIO_TOLERANCE", "MAX_RATIO", "OneRendering", "block_codes",
                         "intensity_mappings", "one_rendering", "frame_predictions", "DECIMATE_ABOVE",
                         "bracket_one_rendering"],
    "roundtrip": ["FAIL_CODES", "REGIONS", "SHIFT_BLOCK", "SHIFT_STEP", "RoundTrip", "round_trip", "tolerant_residual",
                  "box_means", "inverse_tables", "bracket_black", "bracket_round_trip", "FLOOR_PIXELS", "replay_alignment"],
    "families": ["TUNING_FAMILIES", "FAMILY_METHODS", "PEERS", "MIN_SMOOTH_PIXELS", "opencv_merge", "smooth_mask", "family_comparison", "summarise_families"],
})
