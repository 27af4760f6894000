"""HDR merge methods: the registry, the classic merges, paper 1 (stabilisation) and paper 2 (probabilistic HDR).

Modules: :mod:`derender.hdr.batch`, :mod:`derender.hdr.classic`, :mod:`derender.hdr.files`, :mod:`derender.hdr.lognormal`, :mod:`derender.hdr.probabilistic`, :mod:`derender.hdr.probabilistic_variance`, :mod:`derender.hdr.raw`, :mod:`derender.hdr.raw_align_deghost` (its alignment and ghost removal), :mod:`derender.hdr.registry`, :mod:`derender.hdr.stabilize`, :mod:`derender.hdr.stabilized_probabilistic`, :mod:`derender.hdr.summary`.
"""

from derender.core.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "batch": ["stack_files", "merge_one_stack", "merge_batch"],
    "classic": ["bracket_variance", "DebevecOptions", "RobertsonOptions", "DebevecMethod", "RobertsonMethod", "merge_debevec", "merge_robertson", "debevec_stack", "robertson_stack"],
    "files": ["merge_files"],
    "probabilistic": ["CODE_NOISE", "product_of_gaussians", "as_model", "merge_probabilistic", "ProbabilisticOptions", "probabilistic_engine", "probabilistic_stack", "saturation_mask", "finite_outputs", "check_options", "ProbabilisticMethod", "log_product_moments"],
    "lognormal": ["MAX_LOG", "MAX_V", "truncnorm_moments", "truncate_below", "truncate_below_log"],
    "probabilistic_variance": ["K_MODEL", "K_PIPE", "K_SPATIAL", "add_spatial", "model_sd", "fill_model_sd", "shared_log_moments"],
    "stabilized_probabilistic": ["colour_reliability", "colour_weight_table", "StabilizedProbabilisticMethod", "StabilizedProbabilisticOptions", "merge_stabilized_probabilistic", "stabilized_probabilistic_stack"],
    "raw": ["ESTIMATORS", "RawOptions", "merge_raw", "check_one_camera", "merge_raw_files"],
    "raw_align_deghost": [],
    "registry": ["MethodSpec", "METHODS", "method_spec", "register_method", "get_method", "method_options", "seeded_options", "merge", "merge_seeded", "merge_stack", "run_engine", "settable_options", "parse_options"],
    "summary": ["FrameRecord", "MergeSummary", "merge_summary_record", "attach_summary", "SUMMARY_ATTRIBUTE", "SUMMARY_HEADER"],
})
