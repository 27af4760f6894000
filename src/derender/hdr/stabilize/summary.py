"""What a stabilised merge reports: the ``HDRResult.info`` record of a
:class:`~derender.hdr.stabilize.method.Stabilization` (:func:`stabilization_info`) and the note
printed when the merge's mode cannot matter (:func:`mode_note`)."""

from __future__ import annotations

from typing import Any

__all__ = ["stabilization_info", "mode_note"]


def mode_note(stab: Any) -> str | None:
    """The sentence a merge prints when its mode cannot matter: a bracket that
    :func:`~derender.hdr.stabilize.colour_matrices.diagonal_bracket` finds to be one rendering
    up to per-channel gains takes every matrix from one set of gains in both modes
    (:func:`~derender.hdr.stabilize.colour_matrices.graph_gains`), and the grey balance takes out
    the one diagonal by which the modes (and the references) differ: ``stabilized`` and
    ``stabilized-joint`` then give the same map up to one global factor (measured: Frobisher
    1.0023, the sculpture garden 1.050, every pixel within 4e-7 of it; a fixed ``simple``
    simulator bracket 0.958 within 1.3e-4). None when the bracket's
    colour model is the full per-frame fit, where the modes differ."""
    cm = stab.info.get("colour_model") or {}
    if not cm.get("diagonal"):
        return None
    other = "stabilized" if stab.mode == "joint" else "stabilized-joint"
    return (f"colour model: one rendering (per-channel gains fit the whole bracket, diagonal ratio "
            f"{float(cm.get('diagonal_ratio', float('nan'))):.3f}): the {stab.mode} fit equals the "
            f"{'reference' if stab.mode == 'joint' else 'joint'} fit here, {other} gives the same map "
            f"(up to one global factor)")


def stabilization_info(stab: Any) -> dict:
    """What a stabilised merge reports in ``HDRResult.info``."""
    al = stab.alignment
    info = {"reference": stab.reference, "gammas": stab.gammas.gammas.tolist(),
            "gamma_method": stab.gammas.method, "matrices": stab.matrices.tolist(), "mode": stab.mode,
            "how": stab.how, "align": al.method, "response": stab.info.get("response", "given"),
            "gamma_trend": stab.info.get("gamma_trend")}
    if stab.gammas.method == "curve" and "rho" in stab.gammas.info:
        info["rho"] = stab.gammas.info["rho"]          # per-frame relative exponents of the curve model
        info["curve_misfit"] = stab.gammas.info.get("misfit")   # (rho = 1, fitted rho) per channel
    if "hidden_saturation" in stab.info:
        info["hidden_saturation"] = stab.info["hidden_saturation"]
    if "grey_balance" in stab.info:
        info["grey_balance"] = stab.info["grey_balance"]
    if "gamma_level" in stab.info:
        info["gamma_level"] = stab.info["gamma_level"]
    if "shape_tie" in stab.info:
        info["shape_tie"] = stab.info["shape_tie"]
    if "colour_model" in stab.info:
        info["colour_model"] = stab.info["colour_model"]
    note = mode_note(stab)
    if note:
        info["note"] = note
    if al.shifts is not None:
        info["shifts"] = al.shifts.tolist()
    return info
