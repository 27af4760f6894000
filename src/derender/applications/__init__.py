"""Uses of de-rendered radiance: Lambertian photometric stereo weighted by inverse variances (paper 2, Sec. 4.3).

Modules: :mod:`derender.applications.photometric_stereo`.
"""

from derender.core.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "photometric_stereo": ["PhotometricScene", "sphere", "bumps", "default_lights", "read_lights", "solve_normals", "angular_error_deg", "frankot_chellappa", "render_photometric_images"],
})
