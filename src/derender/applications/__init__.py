"""Uses of radiance maps: Lambertian photometric stereo weighted by inverse variances (paper 2, Sec. 4.3) and
the self-contained HTML report.

Modules: :mod:`derender.applications.photometric_stereo`, :mod:`derender.applications.report`.
"""

from derender.core.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "photometric_stereo": ["PhotometricScene", "sphere", "bumps", "default_lights", "read_lights", "solve_normals", "angular_error_deg", "frankot_chellappa", "render_photometric_images"],
    "report": ["REPORT_MAX_PIXELS", "RGB_MANTISSA_BITS", "VAR_MANTISSA_BITS", "reduce_map", "pack_half", "write_report"],
})
