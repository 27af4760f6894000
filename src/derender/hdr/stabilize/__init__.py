"""Pipeline-aware exposure fusion (paper 1, Sec. 3, Algorithm 1) and a reference-free variant.

Model (paper 1, eq. 4 and 8): image ``j`` of a bracket renders the sensor exposure
``x t_j`` as ``J_j = clip(A_j x t_j, 0, 1) ** (1 / gamma_j)`` with a per-image 3x3 matrix
``A_j`` (white balance, colour matrix, gain) and a per-image *display gamma*
``gamma_j`` (the encoding exponent is ``1 / gamma_j``; every gamma in this module is the
display gamma, ~2.2). Undoing the gamma gives linear images ``L_j = J_j ** gamma_j``
which are related by 3x3 matrices (eq. 9): ``L_ref = H_j L_j`` with
``H_j = A_ref A_j^-1 t_ref / t_j``. Steps (Algorithm 1):

1. :func:`select_reference` -- the best-exposed image (fewest over/under-exposed pixels).
2. Registration -- :func:`derender.hdr.align.align_images` (MTB translation by default).
3. Per-image linearisation -- :func:`estimate_gammas` (a display gamma per image; with
   times or blind). When those gammas drift steadily with exposure time the tone curve
   is not a power law (film, filmic picture styles) and ``response="auto"`` switches to
   one common Debevec & Malik curve (:func:`power_law_plausible`, :class:`Curve`), fitted
   on samples away from clipped pixels (:func:`unclipped_debevec`). A quick search runs
   first and sends clearly filmic brackets to the curve straight away
   (:data:`SCREEN_TREND`).
4. :func:`fit_color_matrix` / :func:`color_matrices_to_reference` -- H_j by weighted
   least squares inside a seeded RANSAC, clipped and dark pixels left out (eq. 9-10).
   **The exposure ratio is absorbed in H_j** (as the paper does after eq. 9): H_j maps
   image j's linear values onto the reference's, so the stabilised images
   ``I'_j = H_j L_j`` (eq. 10) are all in the reference's exposure and colour rendering;
   the merge divides by ``t_ref``. Wrong EXIF times and gain changes therefore do not
   bias the colours (times serve the gamma level, the noise weights and the joint gauge).
5. :func:`stabilized_merge` -- trapezoid-weighted average through
   :func:`derender.engine.reference.merge_linear` (method ``"stabilized"``), by default also
   weighted by each estimate's inverse noise variance.

Fits use 2x2-pixel block means of the linearised values (noise in both images biases
pixel-wise fits; block means keep the linear relation exact) and pixels whose
channels all lie in (FIT_LOW, FIT_HIGH) in the brighter image of a pair.

Beyond the paper (its Fig. 5: the result depends on the reference):
:func:`joint_color_matrices` fits all ``K_j`` at once so that ``K_j L_j / t_j`` agree on
every overlapping pair of images, with the gauge ``mean_j K_j = I`` (times folded in),
i.e. a common linear space equal to the bracket's *average* rendering, no reference at
all (method ``"stabilized-joint"``). :func:`reference_spread` reports how PSNR varies
with the reference.
"""

from derender.core.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "estimate": ["make_blocks", "estimate_gammas_blocks", "screen_gamma_trend", "curve_model", "REF_LOW", "REF_HIGH", "REF_PIXELS", "FIT_LOW", "FIT_HIGH", "FIT_FLOOR", "exposure_fractions", "select_reference", "RIDGE", "Curve", "NARROW", "XATOL", "GammaEstimate", "estimate_gammas", "gamma_trend", "SCREEN_TREND", "power_law_plausible", "CURVE_CLIP", "CURVE_CLIP_RADIUS", "CURVE_SAMPLES", "unclipped_debevec", "fit_color_matrix", "color_matrices_to_reference", "joint_color_matrices", "reasonable_references"],
    "method": ["Stabilization", "stabilize", "stabilize_aligned", "stabilized_merge", "stabilization_info", "merge_stabilized", "merge_stabilized_joint", "merge_stabilized_table", "stabilized_plan", "StabilizedMethod", "ShiftedFrames", "ShiftedValid", "LazyAlignment"],
})
