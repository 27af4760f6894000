"""Pipeline-aware exposure fusion (paper 1, Sec. 3.1, Algorithm 1) and a reference-free variant.

Model (paper 1, eq. 4 and 8): image ``j`` of a bracket renders the sensor exposure
``x t_j`` as ``J_j = clip(A_j x t_j, 0, 1) ** (1 / gamma_j)`` with a per-image 3x3 matrix
``A_j`` (white balance, colour matrix, gain) and a per-image *display gamma*
``gamma_j`` (the encoding exponent is ``1 / gamma_j``; every gamma in this package is the
display gamma, ~2.2). Undoing the gamma gives linear images ``L_j = J_j ** gamma_j``
which are related by 3x3 matrices (eq. 9): ``L_ref = H_j L_j`` with
``H_j = A_ref A_j^-1 t_ref / t_j``. Algorithm 1, one module per step:

* Step 1, :mod:`derender.engine.motion.reference_frame` -- :func:`~derender.engine.motion.reference_frame.select_reference`, the best-exposed image (fewest
  over/under-exposed pixels).
* Step 2, registration -- :func:`derender.engine.motion.align.align_images` (Ward's MTB translation by
  default, :mod:`derender.engine.motion.ward2003`).
* Step 3.1, per-image linearisation, :mod:`.exponents` -- :func:`estimate_gammas` (a display gamma
  per image, blind pairwise searches; absolute level with times or blind), read through
  the :class:`Curve` linearisations of :mod:`.curves`. When those gammas drift steadily
  with exposure time the tone curve is not a power law (film, filmic picture styles) and
  ``response="auto"`` switches to one common Debevec & Malik curve (:mod:`.filmic`:
  :func:`power_law_plausible`, :func:`curve_model`), fitted on samples away from clipped
  pixels (:func:`unclipped_debevec`, its samples in :mod:`.curve_samples`; beyond Debevec & Malik, per-frame exposure offsets
  re-estimated with the curve, :data:`CURVE_EXPOSURE_ROUNDS`). A quick search runs first and sends clearly filmic
  brackets to the curve straight away (:data:`SCREEN_TREND`).
* Step 3.2, :mod:`.colour_matrices` -- :func:`fit_frame_matrix` / :func:`colour_matrices_to_reference`:
  H_j by weighted least squares inside a seeded RANSAC, clipped and dark pixels left out
  (eq. 9-10). **The exposure ratio is absorbed in H_j** (as the paper does after eq. 9):
  H_j maps image j's linear values onto the reference's, so the stabilised images
  ``I'_j = H_j L_j`` (eq. 10) are all in the reference's exposure and colour rendering;
  the merge divides by ``t_ref``. Wrong EXIF times and gain changes therefore do not bias
  the colours (times serve the gamma level, the noise weights and the joint gauge). Beyond the
  paper: when the frames' exposures follow their times (one rendering; the gamma level's check,
  :data:`TIME_FOLLOW`), each matrix's luminance scale is set from the times instead
  (:func:`anchor_to_times`): a fit to a frame 8-10 stops from the reference reads its
  noisy dark codes and carried 0.935-0.941 of the time ratio.
  Brackets whose frames differ by per-channel gains only (one rendering: a fixed pipeline, a
  film) take gains consistent over all neighbour pairs instead (:func:`diagonal_bracket`,
  :func:`graph_gains`): then the map does not depend on the reference (beyond the paper).
  :mod:`.colour_model` runs this step for the merges (:func:`fit_colour_model`: matrices, time
  anchoring, grey balance).
* Step 4, :mod:`.method` -- :func:`stabilized_merge`, trapezoid-weighted average through
  :func:`derender.engine.float_merge.merge_linear` (method ``"stabilized"``), by default also
  weighted by each estimate's inverse noise variance; :func:`stabilize` runs steps 1-3.2;
  :mod:`.summary` makes the ``info`` record it reports.

Fits use 2x2-pixel block means of the linearised values (:mod:`.blocks`: noise in both
images biases pixel-wise fits; block means keep the linear relation exact) and pixels
whose channels all lie in (FIT_LOW, FIT_HIGH) in the brighter image of a pair. The 3x3
map of a pair and its code-domain misfit, which both the gamma searches and the colour
matrices use, are in :mod:`.pair_fit`; the scalar searches (Brent's methods) in
:mod:`.solvers`.

Beyond the paper (its Fig. 5: the result depends on the reference):
:func:`joint_colour_matrices` fits all ``K_j`` at once so that ``K_j L_j / t_j`` agree on
every overlapping pair of images, with the gauge ``mean_j K_j = I`` (times folded in),
i.e. a common linear space equal to the bracket's *average* rendering, no reference at
all (method ``"stabilized-joint"``). Both modes then grey-balance the output (:mod:`.grey_balance`,
the neutral axis): one gain per channel, from the blocks the frames render neutral, multiplies every
H_j / K_j, so that greys come out grey whatever gauge the per-channel curves left. Pipelines that render a sensor-clipped pixel below
white (local tone maps, highlight roll-offs) are caught by :mod:`.saturation`: codes that
stop growing with exposure mark saturation no threshold sees, and the merges leave it out.
:func:`derender.evaluation.table1.reference_spread` reports how PSNR varies with the reference.
"""

from derender.core.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "blocks": ["FIT_LOW", "FIT_HIGH", "FIT_FLOOR", "Blocks", "make_blocks"],
    "colour_matrices": ["DIAGONAL_GAIN", "fit_frame_matrix", "colour_matrices_to_reference", "joint_colour_matrices",
                        "diagonal_bracket", "graph_gains"],
    "curves": ["Curve", "as_curve", "MIN_LOG_SLOPE"],
    "grey_balance": ["GREY_BALANCE", "GREY_TOLERANCE", "GREY_MIN_BLOCKS", "GREY_MAX_GAIN", "grey_balance"],
    "exponents": ["NARROW", "XATOL", "TIME_FOLLOW", "relative_exponents", "GammaEstimate", "estimate_gammas", "estimate_gammas_blocks"],
    "filmic": ["gamma_trend", "SCREEN_TREND", "screen_gamma_trend", "power_law_plausible", "CURVE_TIE", "CURVE_TIE_CODES", "CURVE_SHAPE_TIE", "CURVE_EXPOSURE_ROUNDS", "CURVE_OFFSET_PRIOR", "CURVE_OFFSET_DEGREE", "CURVE_MAX_OFFSET", "CURVE_EXPONENT_ROUNDS", "unclipped_debevec", "curve_model"],
    "curve_samples": ["CURVE_CLIP", "CURVE_CLIP_RADIUS", "CURVE_BIN_MIN", "CURVE_BIN_WIDTH", "CURVE_BIN_CODES",
                      "CURVE_BIN_CANDIDATES", "CURVE_SAMPLES", "unclipped_samples", "codes_at_positions",
                      "sparse_bin_samples"],
    "colour_model": ["fit_colour_model", "anchor_to_times"],
    "summary": ["stabilization_info", "mode_note"],
    "method": ["Stabilization", "stabilize", "stabilize_aligned", "stabilized_merge", "merge_stabilized", "merge_stabilized_joint", "merge_stabilized_table", "stabilized_plan", "StabilizedMethod", "StabilizedOptions", "stabilized_engine", "stabilized_joint_engine", "stabilized_stack", "stabilized_joint_stack"],
    "frame_exponents": ["EXPONENT_DEGREE", "EXPONENT_MAX", "EXPONENT_STEP", "EXPONENT_GRID", "EXPONENT_FREE_OFFSETS",
                        "warp_codes", "interp_table", "search_exponents", "gauge_exponents"],
    "frame_views": ["ShiftedFrames", "ShiftedValid", "HeldValid", "CodeFrameRows", "LazyAlignment"],
    "pair_fit": ["RIDGE", "predict_codes", "pair_weights", "fit_pair", "effective_codes", "pair_cost", "pair_residuals", "pair_costs_power"],
    "saturation": ["STAGNATION_CODES", "STAGNATION_FLOOR", "STAGNATION_CEILING", "STAGNATION_RATIO",
                   "HIDDEN_FRACTION", "hidden_saturation", "hidden_fraction", "saturation_fraction",
                   "saturation_mask"],
    "solvers": ["minimize_bounded", "bounded_minimizer", "drive", "find_root"],
})
