"""The engine's motion stage: reference frame, alignment and ghost removal, for every method.

Real brackets are shot by hand and things move in them. The motion run
(:func:`derender.engine.motion.run.run_motion`) is the engine's path for such brackets,
beside the plain run (:func:`derender.engine.run.run`); the caller chooses
(:func:`derender.hdr.files.merge_files`, :func:`derender.hdr.registry.merge`). It builds on
the plain engine (frame sources, plans, kernels: :mod:`derender.engine.frames`), which never
imports it.

Modules, in the order the run uses them:

* :mod:`derender.engine.motion.run` -- the motion run and its options
  (:class:`~derender.engine.motion.run.MotionOptions`);
* :mod:`derender.engine.motion.reference_frame` -- choosing the reference frame (paper 1, Sec. 3.1);
* :mod:`derender.engine.motion.ward2003`, :mod:`derender.engine.motion.align` -- registering the
  frames to it (Ward's median threshold bitmaps; features and a homography);
* :mod:`derender.engine.motion.deghost`, :mod:`derender.engine.motion.intensity_mapping`, :mod:`derender.engine.motion.ghost_kernels` -- the
  consistency test of every frame against the reference through intensity mapping functions learnt from the bracket;
* :mod:`derender.engine.motion.compensation` -- filling rejected pixels from each frame's
  flow-compensated view;
* :mod:`derender.engine.motion.consensus` -- removing the rendering bias of the frames left
  where ghost removal left some out;
* :mod:`derender.engine.motion.censored_fill` -- where ghost removal left only clipped frames,
  filling the bound from the measured clipped scene around it.
"""

from derender.core.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "run": ["MotionOptions", "resolve_reference", "align_frames", "refine_shifts", "bitmap_agreement", "check_one_scene", "run_motion", "REFINE_PIXELS", "REFINE_REACH", "MIN_BITMAP_AGREEMENT", "SCENE_CHECK_PIXELS"],
    "reference_frame": ["REF_LOW", "REF_HIGH", "REF_PIXELS", "check_images", "exposure_fractions", "select_reference", "reasonable_references"],
    "ward2003": ["to_grey8", "grey8_codes", "median_threshold_bitmaps", "common_percentiles", "common_percentiles_hist", "MTB_PIXELS", "mtb_shift"],
    "align": ["ALIGNMENTS", "Alignment", "shift_into", "shift_valid", "shift_image", "estimate_homography", "warp_image", "align_images", "transforms_to_shifts", "chain_transforms", "exposure_lut", "block_displacements", "residual_flow", "flow_warp", "FLOW_SIDE", "FLOW_CODES", "FLOW_MIN_GRADIENT", "FLOW_CONSISTENCY", "FLOW_SIGMA", "FLOW_PRIOR", "FLOW_MIN_PX", "FLOW_GATE_PX", "FLOW_MIN_PEAK", "FLOW_MAX_PX"],
    "deghost": ["GHOST_THRESHOLD", "GHOST_WINDOW", "GHOST_DILATE", "CODE_SIGMA", "DETECT_PIXELS", "STAT_PIXELS", "MAX_REJECTED", "REFIT_MIN_REJECTED", "Z2_CAP", "EDGE_SHIFT", "AGREEMENT_MIN_PIXELS", "frame_estimates", "FrameAgreement", "ConsistencyTest", "upsample_mask", "map_frames", "detect_ghosts", "merge_valid"],
    "intensity_mapping": ["MIN_PIXELS", "SIGMA_FLOOR", "MappingTables", "mapping_tables", "mapping_z2"],
    "ghost_kernels": ["upsample_into"],
    "compensation": ["FLOW_CHECK", "FLOW_PIXELS", "compensate_frames"],
    "consensus": ["CONSENSUS_BIN", "CONSENSUS_MIN_COUNT", "CONSENSUS_PIXELS", "frame_biases", "consensus_correct"],
    "censored_fill": ["CENSOR_CODE", "DATA_TOL", "PYRAMID_LEVELS", "W_FULL", "hidden_views", "pull_push", "censored_fill"],
})
