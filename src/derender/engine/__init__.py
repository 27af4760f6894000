"""The merge engine: frames decoded in threads, reference frame, alignment and ghost removal, 256-entry table and 3x3-matrix kernels, accumulation, saturation policy.

Modules: :mod:`derender.engine.align`, :mod:`derender.engine.compensation`, :mod:`derender.engine.deghost`, :mod:`derender.engine.frames`, :mod:`derender.engine.ghost_kernels`, :mod:`derender.engine.kernels`, :mod:`derender.engine.matrix`, :mod:`derender.engine.overlap`, :mod:`derender.engine.reference`, :mod:`derender.engine.reference_frame`, :mod:`derender.engine.tables`, :mod:`derender.engine.table_kernel`, :mod:`derender.engine.variance`, :mod:`derender.engine.variance_kernels`, :mod:`derender.engine.motion`, :mod:`derender.engine.ward2003`, :mod:`derender.engine.weights`.
"""

from derender.core.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "frames": ["NotStreamable", "prefetch", "FramePool", "read_frames", "FileFrames", "ArrayFrames", "clipped_pixels", "frame_brightness", "merge_held", "STREAMED_BYTES_PER_PIXEL"],
    "outputs": ["write_outputs", "write_while_merging", "motion_attributes"],
    "kernels": ["MERGE_TILE", "stabilized_merge_rows", "mtb_band_counts", "table_merge_rows", "gaussian_band", "mark_colours", "normal_cdf", "table_mu"],
    "merge_parts": ["add_frame_to_tile", "add_table_observation", "fallback_frame"],
    "compensation": ["FLOW_CHECK", "FLOW_PIXELS", "compensate_frames"],
    "matrix": ["merge_matrix_frames", "matrix_output_bytes", "KERNEL_LOCK", "set_numba_threads", "warm_up_kernels"],
    "reference": ["merge_linear"],
    "reference_frame": ["REF_LOW", "REF_HIGH", "REF_PIXELS", "check_images", "exposure_fractions", "select_reference", "reasonable_references"],
    "tables": ["code_histograms", "code_table", "F32_MAX", "code_values", "weight_table", "curve_value_tables", "stack_codes_exact", "TableMerge", "merge_codes", "merge_curves_table"],
    "weights": ["F32_MAX", "weight_hat", "weight_trapezoid", "weight_gaussian", "WEIGHTS", "get_weight"],
    "gaussian": ["LogGaussianProduct", "merge_gaussian_frames", "mark_colours_held"],
    "overlap": ["OVERLAP_ROWS", "RING_SLOTS", "RowsDone", "OutputRing", "merge_writing", "run_bands"],
    "plans": ["FrameAccess", "TablePlan", "MatrixPlan", "GaussianPlan", "EngineMethod", "MethodDefaults"],
    "align": ["ALIGN_METHODS", "Alignment", "shift_into", "shift_valid", "shift_image", "estimate_homography", "warp_image", "align_images", "transforms_to_shifts", "chain_transforms"],
    "ward2003": ["to_grey8", "grey8_codes", "median_threshold_bitmaps", "common_percentiles", "common_percentiles_hist", "MTB_PIXELS", "mtb_shift"],
    "run": ["run", "run_stack", "ENGINES", "HOLD_BYTES", "KERNEL_MIN_PIXEL_FRAMES"],
    "table_kernel": ["table_kernel_merge", "warm_up_kernel"],
    "variance": ["VarianceModel", "METHOD_CONSTANTS", "method_constants", "variance_tables", "matrix_variance_tables", "add_edge_term", "source_shares", "SOURCES", "SHOT", "READ", "SHARED", "INFLATE", "INFLATE_DIS", "INFLATE_SYS", "EDGE", "CENSORED", "R_FLOOR", "SOURCE_STRIDE"],
    "variance_kernels": ["table_merge_var_rows", "stabilized_merge_var_rows"],
    "motion": ["ALIGNMENTS", "MotionOptions", "resolve_reference", "align_frames", "refine_shifts", "bitmap_agreement", "check_one_scene", "run_motion"],
    "ghost_kernels": ["ghost_statistic"],
    "deghost": ["GHOST_THRESHOLD", "GHOST_WINDOW", "GHOST_DILATE", "CODE_SIGMA", "DETECT_PIXELS", "MAX_REJECTED", "frame_estimates", "detect_ghosts", "merge_valid"],
})
