"""RAW development: the binary-weight merge of paper 1 (Sec. 4.2, Alg. 2), white balance, demosaicing, ground truth in linear sRGB.

Modules: :mod:`derender.raw.groundtruth`, :mod:`derender.raw.mosaic`.
"""

from derender.core.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "groundtruth": ["raw_to_camera_rgb", "raw_ground_truth"],
    "mosaic": ["LOW", "HIGH", "DEMOSAIC_METHODS", "sorted_raw_frames", "cfa_channel_index", "merge_raw_mosaics", "white_balance_mosaic", "wb_from_patch", "demosaic_bayer", "spread_mask", "finite_float32"],
})
