"""Photometry: lens projections, luminance in cd/m2 and illuminance from radiance maps.

Modules: :mod:`derender.photometry.projection` (Radiance views: each pixel's direction and
solid angle), :mod:`derender.photometry.illuminance` (luminance of a map, vertical
illuminance Ev as Radiance's ``evalglare -V`` computes it), :mod:`derender.photometry.calibration`
(the photometric factor from a luminance-meter spot reading), :mod:`derender.photometry.falsecolor`
(falsecolor luminance with a legend), :mod:`derender.photometry.vignetting` (radial falloff
from a flat field), :mod:`derender.photometry.profile` (camera profiles: curves, factor,
vignetting, view, reused across brackets).
"""

from derender.core.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "projection": ["View", "parse_view", "pixel_directions", "pixel_solid_angles"],
    "vignetting": ["VIGNETTING_FORMAT", "Vignetting", "fit_vignetting", "correct_vignetting", "save_vignetting",
                   "load_vignetting"],
    "falsecolor": ["falsecolor_figure", "scale_top"],
    "calibration": ["Spot", "parse_spot", "SpotCalibration", "spot_factor", "ISO2720_K", "ISO12232_Q",
                    "MID_GREY_CODE", "MID_GREY_LINEAR", "SensitivityRating", "SENSITIVITY_RATINGS",
                    "sensitivity_rating", "ExifCalibration", "exif_factor"],
    "profile": ["PROFILE_FORMAT", "REFERENCE_EXPOSURE", "CameraProfile", "save_profile", "load_profile",
                "factor_at_reference", "factor_for_bracket", "curves_from_rsp", "rsp_from_curves", "camera_mismatch",
                "CURVE_METHODS"],
    "illuminance": ["RADIANCE_EFFICACY", "RADIANCE_LUMINANCE_WEIGHTS", "luminance_weights", "luminance_cd_m2",
                    "vertical_illuminance", "IlluminanceResult"],
})
