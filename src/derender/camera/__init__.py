"""Physically based camera simulator with exact truth.

The simulator renders a *spectral* scene through a camera's measured spectral
sensitivities into a noisy Bayer mosaic (shot + read noise, black/white level, 12/14-bit
ADC), writes it as a real DNG, and renders the in-camera JPEG from that mosaic (demosaic,
white balance, camera-to-sRGB matrix, gain, tone rendering, gamut handling, 8-bit), with
EXIF ``ExposureTime``; the JPEG engine also applies a mild chroma noise reduction, as cameras
do before chroma subsampling. The scene radiance is known exactly, so every later stage is judged
against truth.

Data flow::

    make_scene(kind, size, seed)         -> SpectralScene (reflectance + illumination maps)
    scene_camera_rgb(scene, camera)      -> camera RGB per second, noise-free (H, W, 3)
    simulate_bracket(...)                -> SimulatedBracket (mosaics, JPEG codes, times, truth)
    write_bracket(bracket, outdir)       -> raw/NN.dng, jpeg/NN.jpg, truth.exr, scene.json

Truth (``truth.exr``) is the white-balanced, noise-free, unclipped camera RGB per second
mapped to linear sRGB by the same normalised colour matrix a RAW converter derives from the
DNG's ColorMatrix1 (:func:`derender.colorimetry.camera_to_linear_srgb_matrix`)
with the DNG's AsShotNeutral white balance: the quantity paper 1 (Sec. 4.2) builds from RAW.

Pipelines
---------
``fixed``: every exposure rendered identically (white balance of the scene illuminant,
gain 1, display gamma 2.2, no saturation change).

``auto`` (what auto modes do; magnitudes drawn from a seeded generator, stored in
``scene.json``): per exposure j the white-balance multipliers drift across the bracket by
up to +-10 % (R) and -+8 % (B) plus 4 % random jitter (log-normal); gain alpha_j =
exp(U(0, 0.3)), i.e. 1 to 1.35 (never below 1, so a saturated sensor still renders as
255, as in real cameras); display gamma gamma_j ~ U(1.8, 2.6) (encoding
exponent 1/gamma_j); a saturation matrix s_j ~ U(0.85, 1.15). The DNGs always carry the
scene's true white balance (AsShotNeutral), so the RAW ground truth is the same for both.

Pipeline families
-----------------
``simulate_bracket(..., family=F)`` (``derender simulate OUTDIR --render F``) renders through
one of :data:`derender.camera.families.FAMILIES`, so that methods can be tuned on some families
and reported on held-out others: ``paper`` (paper 1's eq. 4: the ``simple`` style with the
``auto`` pipeline, byte for byte), ``camera`` (the default: ``camera`` style, ``auto``, byte
for byte), ``dslr-lut`` (a DSLR engine after Kim et al., PAMI 2012: white balance inside the
3x3, hue-dependent saturation, a random smooth 3D gamut LUT, per-channel tone curves, white
balance switching between presets), ``phone-local`` (a local tone map: a smooth gain map from
the frame's blurred luminance sets the shadow gain of a curve that keeps white; per-frame gain
and gamma) and ``drift``
(white balance and gain drifting continuously: a harder ``auto``). Each frame's parameters are a
:class:`derender.camera.stages.FrameSettings` (``SimulatedBracket.frames``, ``scene.json``'s
``"frames"``; :func:`derender.camera.bracket.load_frame_settings` reads them back, and
:func:`derender.camera.stages.render_frame` re-renders the codes from the mosaics exactly);
:func:`derender.camera.oracle.invert_frame_codes` inverts them (the oracle of
:mod:`derender.evaluation.oracle`).

Rendering styles
----------------
``simple``: ``y = clip(alpha_j S_j M WB_j x, 0, 1) ** (1 / gamma_j)`` - exactly the model
of paper 1 (its eq. 4), optionally followed by a fixed S-shaped tone curve (``tone_curve``).

``camera`` (default, like a real picture style): saturation boost 1.2, soft hue-preserving
gamut compression (chroma scaled towards luminance so no channel goes negative, with a soft
knee), a per-channel filmic S-curve with highlight shoulder (Hable's curve, exposure bias 6,
white at linear 1 = sensor saturation), then the display gamma with a linear toe (as
sRGB: finite slope at black). The ``simple`` style keeps the pure power law of paper 1. No 3x3-plus-curve model contains it.

Modules: :mod:`derender.camera.spectral` (spectral data, cameras), :mod:`derender.camera.scene` (scenes),
:mod:`derender.camera.sensor` (mosaic, noise), :mod:`derender.camera.rendering` (in-camera pipeline),
:mod:`derender.camera.stages` (per-frame settings and stages), :mod:`derender.camera.families` (pipeline
families), :mod:`derender.camera.oracle` (their exact inverse),
:mod:`derender.camera.bracket` (brackets and files), :mod:`derender.camera.motion` (moving objects, camera shake), :mod:`derender.camera.dng` (DNG writer),
:mod:`derender.camera.chart` (calibration charts), :mod:`derender.camera.luminance` (the luminance-truth family:
absolute cd/m2 over 5 decades, EXIF t/N/ISO, a grey card, vignetting, flat fields).
"""

from derender.core.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "chart": ["PAIRS_FORMAT", "PAIRS_VERSION", "colorchecker_sg_reflectances", "gel_illuminants", "chart_exposures", "ChartPairs", "chart_pairs", "save_pairs", "load_pairs"],
    "dng": ["to_rational", "write_dng"],
    "spectral": ["WAVELENGTHS", "CameraSpectral", "builtin_camera_names", "load_camera_file", "load_camera", "reflectance_library", "illuminant_spd", "cmfs_xyz", "camera_search_dirs", "camera_search_order", "available_cameras"],
    "bracket": ["SimulatedBracket", "bracket_times", "simulate_bracket", "write_jpeg", "write_bracket", "load_scene_json", "load_frame_settings", "bracket_paths", "simulate_to_folder"],
    "rendering": ["fit_xyz_to_camera", "white_balance_for", "RenderSettings", "encode_gamma_with_toe", "saturation_matrix", "filmic_curve", "s_curve", "gamut_compress", "demosaic_bilinear", "chroma_denoise", "camera_rgb_from_mosaic", "render_style", "isp_render", "pipeline_settings"],
    "stages": ["STYLES", "FrameSettings", "frame_matrix", "hue_angle", "hue_saturation_factor", "hue_saturation", "gamut_lut", "apply_lut", "channel_curve", "local_gain_grid", "local_curve", "inverse_local_curve", "upsample_gain", "prepare_frame", "render_frame", "settings_to_dict", "settings_from_dict"],
    "motion": ["MotionSpec", "MotionPlan", "plan_motion", "compose_frames", "motion_zones", "ZONE_STATIC", "ZONE_SWEPT", "ZONE_OBJECT", "ZONE_NAMES"],
    "families": ["FAMILIES", "WB_PRESETS", "check_family", "family_settings", "random_gamut"],
    "oracle": ["invert_frame_codes", "invert_frame_values", "invert_curve"],
    "scene": ["SCENE_KINDS", "SpectralScene", "make_scene", "scene_camera_rgb", "scene_xyz", "texture_rgb", "soft_mask"],
    "sensor": ["CFA_PATTERN", "mosaic_signal", "expose_mosaic"],
    "luminance": ["LUMINANCE_MODES", "RENDERS", "TUNING_RENDERS", "SATURATION_EXPOSURE", "luminance_scene", "radial_falloff", "exif_triples", "simulate_luminance", "truth_luminance_cd_m2"],
})
