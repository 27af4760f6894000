"""RAW development: the noise-optimal merge (censored Poisson-Gaussian ML, noise from the frames, a variance),
paper 1's binary-weight merge (Sec. 4.2, Alg. 2), white balance, demosaicing, ground truth in linear sRGB.

Modules: :mod:`derender.raw.ahd`, :mod:`derender.raw.groundtruth`, :mod:`derender.raw.menon`,
:mod:`derender.raw.interpolation` (the demosaic's interpolation error in the variance),
:mod:`derender.raw.mosaic`, :mod:`derender.raw.noise`, :mod:`derender.raw.optimal`,
:mod:`derender.raw.register` (sub-photosite registration), :mod:`derender.raw.colour_ghost_test` (its
ghost test colour by colour beside saturation).
"""

from derender.core.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "groundtruth": ["raw_to_camera_rgb", "raw_ground_truth"],
    "interpolation": ["INTERPOLATION_ESTIMATES", "VARIANCE_TERMS", "interpolation_variance"],
    "noise": ["NoiseModel", "estimate_noise", "estimate_noise_pairs", "estimate_noise_single", "estimate_noise_shifted"],
    "optimal": ["OUTPUT_SPACES", "mosaic_observations", "merge_mosaic_optimal", "demosaic_variance", "output_matrix", "raw_merge"],
    "mosaic": ["LOW", "HIGH", "DEMOSAIC_METHODS", "DEMOSAIC_ALIASES", "MASK_RADIUS", "demosaic_name", "sorted_raw_frames", "cfa_channel_index", "merge_raw_mosaics", "white_balance_mosaic", "wb_from_patch", "demosaic_bayer", "spread_mask", "finite_float32"],
})
