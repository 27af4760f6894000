"""RAW development: the noise-optimal merge (censored Poisson-Gaussian ML, noise from the frames, a variance),
paper 1's binary-weight merge (Sec. 4.2, Alg. 2), white balance, demosaicing, ground truth in linear sRGB.

Modules: :mod:`derender.raw.ahd` (Hirakawa & Parks' demosaic with its variance),
:mod:`derender.raw.groundtruth`, :mod:`derender.raw.menon` (Menon 2007's demosaic with its
variance), :mod:`derender.raw.interpolation` (the demosaic's interpolation error in the
variance), :mod:`derender.raw.mosaic`, :mod:`derender.raw.noise`, :mod:`derender.raw.optimal`,
:mod:`derender.raw.register` (sub-photosite registration), :mod:`derender.raw.window_ghost_test`
(its ghost test on 2x2-window sums), :mod:`derender.raw.colour_ghost_test` (and colour by colour
beside saturation), and the compiled loops the merge and the
demosaic run in, :mod:`derender.raw.kernels` and :mod:`derender.raw.register_kernels` (building
blocks, not re-exported here).
"""

from derender.core.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "ahd": ["ahd_demosaic"],
    "colour_ghost_test": ["colour_ghosts"],
    "groundtruth": ["raw_to_camera_rgb", "raw_ground_truth"],
    "interpolation": ["INTERPOLATION_ESTIMATES", "CHROMA_ESTIMATES", "VARIANCE_TERMS", "interpolation_variance",
                      "chroma_texture", "chroma_phase_matrices"],
    "kernels": [],
    "menon": ["menon_demosaic"],
    "noise": ["NoiseModel", "estimate_noise", "estimate_noise_pairs", "estimate_noise_single",
              "estimate_noise_shifted"],
    "optimal": ["OUTPUT_SPACES", "mosaic_observations", "merge_mosaic_optimal", "demosaic_variance", "output_matrix",
                "white_balances", "raw_merge"],
    "mosaic": ["LOW", "HIGH", "DEMOSAIC_METHODS", "DEMOSAIC_ALIASES", "MASK_RADIUS", "demosaic_name", "sorted_raw_frames", "cfa_channel_index", "merge_raw_mosaics", "white_balance_mosaic", "wb_from_patch", "demosaic_bayer", "spread_mask", "finite_float32"],
    "register": ["refine_shift", "resample_rgb", "resample_mosaic", "raw_merge_shifted"],
    "register_kernels": [],
    "window_ghost_test": [],
})
