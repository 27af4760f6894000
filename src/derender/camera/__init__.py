"""The camera simulator: spectral data, sensor and noise, in-camera rendering pipelines, DNG/JPEG writing, calibration charts.

Modules: :mod:`derender.camera.chart`, :mod:`derender.camera.dng`, :mod:`derender.camera.simulate`, :mod:`derender.camera.spectral`.
"""

from derender.core.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "chart": ["PAIRS_FORMAT", "PAIRS_VERSION", "colorchecker_sg_reflectances", "gel_illuminants", "chart_exposures", "ChartPairs", "chart_pairs", "save_pairs", "load_pairs"],
    "dng": ["to_rational", "write_dng"],
    "simulate": ["SCENE_KINDS", "CFA_PATTERN", "SpectralScene", "make_scene", "scene_camera_rgb", "scene_xyz", "fit_xyz_to_camera", "white_balance_for", "mosaic_signal", "expose_mosaic", "RenderSettings", "encode_gamma_with_toe", "saturation_matrix", "filmic_curve", "s_curve", "gamut_compress", "demosaic_bilinear", "chroma_denoise", "isp_render", "pipeline_settings", "SimulatedBracket", "bracket_times", "simulate_bracket", "write_jpeg", "write_bracket", "load_scene_json", "bracket_paths", "simulate_to_folder", "camera_names_for_search"],
    "spectral": ["WAVELENGTHS", "CameraSpectral", "builtin_camera_names", "load_camera_file", "load_camera", "reflectance_library", "illuminant_spd", "cmfs_xyz", "camera_search_dirs"],
})
