"""File formats: rendered images and stacks with EXIF times, RAW/DNG frames, OpenEXR, Radiance RGBE, previews.

Modules: :mod:`derender.io.exif`, :mod:`derender.io.exr`, :mod:`derender.io.files`, :mod:`derender.io.headers`, :mod:`derender.io.images`, :mod:`derender.io.preview`, :mod:`derender.io.raw`, :mod:`derender.io.rgbe`, :mod:`derender.io.rsp` (hdrgen's response files).
"""

from derender.core.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "exif": ["read_exif", "read_exposure_time", "parse_times", "read_times_file", "file_times"],
    "exr": ["write_exr", "read_exr", "EXR_COMPRESSION", "write_exr_fast", "write_exr_lines", "SRGB_CHROMATICITIES",
            "colour_attributes", "exr_attributes", "read_exr_attributes", "fill_exr_attribute", "reserved_text",
            "SUMMARY_BYTES"],
    "files": ["RASTER_SUFFIXES", "RAW_SUFFIXES", "atomic_output", "check_output", "check_not_input",
              "resolve_path", "OutputTransaction", "TEMP_PREFIX",
              "check_input_file", "read_bytes"],
    "headers": ["DEFAULT_MAX_MEGAPIXELS", "ImageInfo", "probe_image", "probe_images", "orient", "jpeg_header"],
    "images": ["read_image", "read_stack", "read_codes"],
    "preview": ["IMAGE8_SUFFIXES", "write_png", "write_preview", "reinhard_photographic", "encode_srgb"],
    "raw": ["read_raw", "read_raw_stack", "read_raw_exposure", "read_raw_bracket"],
    "rsp": ["RSP_MAX_ORDER", "RSP_LINEAR_TOE", "read_rsp", "write_rsp", "rsp_tables", "fit_rsp", "rsp_code_values"],
    "rgbe": ["read_hdr", "read_radiance", "write_hdr", "read_hdr_header", "check_view", "SRGB_PRIMARIES"],
})
