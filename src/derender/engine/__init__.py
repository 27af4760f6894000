"""The merge engine: frames decoded in threads, 256-entry table and 3x3-matrix kernels, accumulation, saturation policy.

Modules: :mod:`derender.engine.frames`, :mod:`derender.engine.kernels`, :mod:`derender.engine.matrix`, :mod:`derender.engine.overlap`, :mod:`derender.engine.reference`, :mod:`derender.engine.tables`, :mod:`derender.engine.weights`.
"""

from derender.core.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "frames": ["NotStreamable", "prefetch", "FramePool", "read_frames"],
    "kernels": ["MERGE_TILE", "stabilized_merge_rows", "mtb_band_counts", "table_merge_rows", "gaussian_band", "mark_colours"],
    "matrix": ["merge_matrix_frames", "matrix_output_bytes", "stabilized_output_bytes", "KERNEL_LOCK", "set_numba_threads", "warm_up_kernels"],
    "reference": ["merge_linear"],
    "tables": ["code_histograms", "F32_MAX", "code_values", "weight_table", "curve_value_tables", "stack_codes_exact", "TableMerge", "merge_codes", "merge_curves_table"],
    "weights": ["F32_MAX", "weight_hat", "weight_trapezoid", "weight_gaussian", "WEIGHTS", "get_weight"],
    "gaussian": ["LogGaussianProduct", "merge_gaussian_frames", "mark_colours_held"],
    "overlap": ["OVERLAP_ROWS", "RING_SLOTS", "RowsDone", "OutputRing", "merge_writing", "run_bands"],
    "plans": ["FrameAccess", "TablePlan", "MatrixPlan", "GaussianPlan", "EngineMethod"],
    "run": ["FileFrames", "ArrayFrames", "run", "run_stack", "write_outputs", "ENGINES"],
})
