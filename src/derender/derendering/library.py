"""Model libraries: pick the de-rendering model of an image's camera from a folder of models.

Paper 2 imagines per-camera models looked up by the metadata of an Internet image:
:func:`resolve_model` loads a model file, or from a *folder* of ``.npz`` models the one
whose stored camera model (``metadata["camera"]``) matches the image's EXIF ``Model``
(case, spaces and punctuation ignored; either name may contain the other).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from derender.core.errors import InputError, ModelFileError
from derender.derendering.base import load_model

__all__ = [
    "resolve_model",
]


def _norm(s: str) -> str:
    return re.sub(r"[^a-z0-9]+", " ", s.lower()).strip()


def _camera_matches(meta_cam: dict, exif: dict) -> bool:
    em = _norm(str(exif.get("Model", "")))
    mm = _norm(str(meta_cam.get("model", "")))
    if not em or not mm:
        return False
    return em == mm or em in mm or mm in em


def camera_mismatch(model, image_path: str | os.PathLike) -> str | None:
    """A one-line note when ``model`` was calibrated for another camera than the one the
    image's EXIF names (None when they match or either side does not say)."""
    from derender.io.exif import read_exif

    cam = model.metadata.get("camera", {}) if isinstance(getattr(model, "metadata", None), dict) else {}
    exif = read_exif(image_path)
    if not cam or not cam.get("model") or not exif.get("Model") or _camera_matches(cam, exif):
        return None
    return (f"the model was calibrated for {camera_label(cam.get('make'), cam.get('model'))}"
            f" but {Path(image_path).name} comes from {camera_label(exif.get('Make'), exif.get('Model'))}")


def camera_label(make: str | None, model: str | None) -> str:
    """``make model`` as people write it: the make once (EXIF often repeats it in the model,
    "Canon" + "Canon PowerShot S90"; rawtoaces names say "NIKON CORPORATION" + "NIKON D5100")."""
    make, model = (make or "").strip(), (model or "").strip()
    if not make:
        return model or "an unnamed camera"
    first = make.split()[0].lower()
    if model.lower().startswith(first):
        return model
    return f"{make} {model}".strip()


def resolve_model(model_path: str | os.PathLike, image_path: str | os.PathLike | None = None):
    """Load ``model_path``; if it is a folder, pick the model matching the image's EXIF camera.

    Returns ``(model, description)``; raises :class:`InputError` when no model matches.
    A single model file is returned whatever camera it was made for: see
    :func:`camera_mismatch` for the check the CLI makes (a warning, or an error with
    ``--strict-camera``).
    """
    from derender.io.exif import read_exif

    p = Path(model_path)
    if p.is_file():
        m = load_model(p)
        return m, p.name
    if not p.is_dir():
        raise InputError(f"no such model file or folder: {p}")
    exif = read_exif(image_path) if image_path is not None else {}
    candidates = []
    for f in sorted(p.glob("*.npz")):
        try:
            m = load_model(f)
        except (ModelFileError, InputError):
            continue
        cam = m.metadata.get("camera", {}) if isinstance(m.metadata, dict) else {}
        candidates.append((f, m, cam))
        if _camera_matches(cam, exif):
            return m, f"{f.name} (camera {camera_label(cam.get('make'), cam.get('model'))} matches the image EXIF)"
    known = ", ".join(f"{f.name}: {c.get('model', '?')}" for f, _, c in candidates) or "none"
    who = f"{exif.get('Make', '?')} {exif.get('Model', '?')}" if exif else "unknown (no EXIF)"
    raise InputError(f"no model in {p} for camera {who}; models: {known}")
