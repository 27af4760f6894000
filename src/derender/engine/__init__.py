"""The merge engine: frame sources and decoding, the plans' kernels (256-entry tables, 3x3 matrices, Gaussians), accumulation, saturation policy, outputs; and its motion stage (reference frame, alignment, ghost removal).

The plain run is :func:`derender.engine.run.run`; the motion run, with its own modules, is
the subpackage :mod:`derender.engine.motion`. Every public name of the modules below is
re-exported here (loaded on first use, :mod:`derender.core.lazy`).

Modules: :mod:`derender.engine.run`, :mod:`derender.engine.options`, :mod:`derender.engine.frames`, :mod:`derender.engine.outputs`, :mod:`derender.engine.plans`, :mod:`derender.engine.tables`, :mod:`derender.engine.table_kernel`, :mod:`derender.engine.matrix`, :mod:`derender.engine.gaussian`, :mod:`derender.engine.kernels`, :mod:`derender.engine.merge_parts`, :mod:`derender.engine.gaussian_kernels`, :mod:`derender.engine.variance`, :mod:`derender.engine.variance_kernels`, :mod:`derender.engine.overlap`, :mod:`derender.engine.weights`, :mod:`derender.engine.float_merge`, :mod:`derender.engine.motion`, :mod:`derender.engine.motion.run`, :mod:`derender.engine.motion.reference_frame`, :mod:`derender.engine.motion.ward2003`, :mod:`derender.engine.motion.align`, :mod:`derender.engine.motion.deghost`, :mod:`derender.engine.motion.intensity_mapping`, :mod:`derender.engine.motion.ghost_kernels`, :mod:`derender.engine.motion.compensation`, :mod:`derender.engine.motion.consensus`.
"""

from derender.core.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "run": ["run", "ENGINES", "KERNEL_MIN_PIXEL_FRAMES"],
    "options": ["OutputOptions", "EngineOptions", "HOLD_BYTES", "KEEP_BYTES"],
    "frames": ["NotStreamable", "prefetch", "FramePool", "read_frames", "FileFrames", "ArrayFrames", "clipped_pixels", "frame_brightness", "merge_held", "STREAMED_BYTES_PER_PIXEL"],
    "outputs": ["write_outputs", "write_while_merging", "motion_attributes"],
    "plans": ["FrameAccess", "TablePlan", "MatrixPlan", "GaussianPlan", "SharedVariance", "EngineMethod", "MethodDefaults"],
    "tables": ["code_histograms", "code_table", "code_values", "weight_table", "curve_value_tables", "stack_codes_exact", "TableMerge", "merge_codes", "merge_curves_table"],
    "table_kernel": ["table_kernel_merge", "warm_up_kernel"],
    "matrix": ["merge_matrix_frames", "matrix_output_bytes", "KERNEL_LOCK", "set_numba_threads", "warm_up_kernels"],
    "gaussian": ["LogGaussianProduct", "merge_gaussian_frames", "mark_colours_held", "variance_sources"],
    "kernels": ["MERGE_TILE", "stabilized_merge_rows", "mtb_band_counts", "table_merge_rows", "gaussian_band", "gaussian_moments_band", "log_tables_rows", "mark_colours", "normal_cdf", "table_mu"],
    "merge_parts": ["add_frame_to_tile", "add_frame_to_tile_var", "add_table_observation", "fallback_frame", "stabilized_observation"],
    "gaussian_kernels": ["NBINS", "gaussian_variance_band", "model_sd_rows"],
    "variance": ["VarianceModel", "add_edge_term", "EDGE", "METHOD_CONSTANTS", "method_constants", "SHARED_BOOTSTRAP", "CURVE_SD_TUNING", "measured_shared", "variance_tables", "matrix_variance_tables", "SOURCES", "source_shares", "SHOT", "READ", "SHARED", "scale_relative_variance", "INFLATE", "INFLATE_DIS", "INFLATE_SYS", "INFLATE_ROBUST", "CENSORED", "R_FLOOR", "SOURCE_STRIDE", "VAR_CAP"],
    "variance_kernels": ["table_merge_var_rows", "stabilized_merge_var_rows", "variance_finish_rows"],
    "overlap": ["OVERLAP_ROWS", "RING_SLOTS", "RowsDone", "OutputRing", "merge_writing", "run_bands"],
    "weights": ["F32_MAX", "weight_hat", "weight_trapezoid", "weight_gaussian", "WEIGHTS", "get_weight", "FLOOR_SHARE", "FLOOR_MIN_COUNT", "FLOOR_MIN_CODE", "FLOOR_MAX_CODE", "FLOOR_PILE", "black_codes", "floor_weights"],
    "float_merge": ["merge_linear"],
    "motion": [],
    "motion.run": ["MotionOptions", "resolve_reference", "align_frames", "refine_shifts", "bitmap_agreement", "check_one_scene", "run_motion", "REFINE_PIXELS", "REFINE_REACH", "MIN_BITMAP_AGREEMENT", "SCENE_CHECK_PIXELS"],
    "motion.reference_frame": ["REF_LOW", "REF_HIGH", "REF_PIXELS", "check_images", "exposure_fractions", "select_reference", "reasonable_references"],
    "motion.ward2003": ["to_grey8", "grey8_codes", "median_threshold_bitmaps", "common_percentiles", "common_percentiles_hist", "MTB_PIXELS", "mtb_shift"],
    "motion.align": ["ALIGNMENTS", "Alignment", "shift_into", "shift_valid", "shift_image", "estimate_homography", "warp_image", "align_images", "transforms_to_shifts", "chain_transforms", "exposure_lut", "block_displacements", "residual_flow", "flow_warp", "FLOW_SIDE", "FLOW_CODES", "FLOW_MIN_GRADIENT", "FLOW_CONSISTENCY", "FLOW_SIGMA", "FLOW_PRIOR", "FLOW_MIN_PX", "FLOW_GATE_PX", "FLOW_MIN_PEAK", "FLOW_MAX_PX"],
    "motion.deghost": ["GHOST_THRESHOLD", "GHOST_WINDOW", "GHOST_DILATE", "CODE_SIGMA", "DETECT_PIXELS", "STAT_PIXELS", "MAX_REJECTED", "REFIT_MIN_REJECTED", "Z2_CAP", "EDGE_SHIFT", "AGREEMENT_MIN_PIXELS", "frame_estimates", "FrameAgreement", "ConsistencyTest", "upsample_mask", "map_frames", "detect_ghosts", "merge_valid"],
    "motion.intensity_mapping": ["MIN_PIXELS", "SIGMA_FLOOR", "MappingTables", "mapping_tables", "mapping_z2"],
    "motion.ghost_kernels": ["upsample_into"],
    "motion.compensation": ["FLOW_CHECK", "FLOW_PIXELS", "compensate_frames"],
    "motion.consensus": ["CONSENSUS_BIN", "CONSENSUS_MIN_COUNT", "CONSENSUS_PIXELS", "frame_biases", "consensus_correct"],
})
