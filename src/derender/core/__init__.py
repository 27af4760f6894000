"""Core types shared by every stage: errors, the Stack / RawFrame / HDRResult dataclasses, colorimetry, parallel helpers.

Modules: :mod:`derender.core.colorimetry`, :mod:`derender.core.errors`, :mod:`derender.core.memory`, :mod:`derender.core.options`, :mod:`derender.core.parallel`, :mod:`derender.core.types`.
"""

from derender.core.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "colorimetry": ["LINEAR_SRGB_TO_XYZ", "XYZ_TO_LINEAR_SRGB", "LUMINANCE_WEIGHTS_REC709", "D65_XYZ", "luminance", "srgb_encode", "srgb_decode", "camera_to_xyz_matrix", "camera_to_linear_srgb_matrix"],
    "errors": ["DerenderError", "InputError", "StackError", "ModelFileError", "Interrupted", "interrupt_handler", "interrupts_deferred"],
    "options": ["check_choice", "check_at_least", "did_you_mean"],
    "memory": ["CHANNELS", "N_CODES", "import_cv2", "opencv_single_thread", "thread_count", "POPULATE_BYTES", "populated_zeros"],
    "parallel": ["run_tasks", "one_blas_thread"],
    "types": ["validate_times", "Stack", "RawFrame", "HDRResult"],
})
