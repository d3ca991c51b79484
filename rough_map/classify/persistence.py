"""Model files: a :class:`~rough_map.classify.TerrainModel` in skops format, and its card.

``save_terrain_model(model, "models/NAME")`` writes

* ``models/NAME.skops``: the model, in the `skops.io <https://skops.readthedocs.io>`_
  format (a zip of JSON and numpy arrays, no pickle);
* ``models/NAME.card.json``: the model card (classes, features, training-data hash,
  cross-validated metrics, library versions) with the sha256 of the model file.

Loading never runs code from the file. skops rebuilds only the types it is told to trust:
its own defaults (numpy, builtins, most of scikit-learn) plus the explicit list
:data:`TRUSTED_TYPES`. A file holding any other type is refused before anything is built,
and so is a file whose sha256 differs from the one its card records (altered after it
was written), a file that is not a skops zip, and one that holds anything but a
``TerrainModel`` of the current :data:`~rough_map.classify.MODEL_FORMAT`.

Before skops parses a file, its zip is bounded (:mod:`rough_map.io._model_archive`: members,
sizes, compression ratio, ``schema.json`` size and nesting, array headers); after, the
rebuilt model's structure is checked and it must pass a trial prediction
(:mod:`rough_map.classify._checks`). Every failure is a one-line :class:`ModelError` naming
the file.

A model and its card are written as one set of files (:func:`rough_map._files.atomic_outputs`):
both into ``.NAME.skops.pending/``, then a ``complete`` marker, then renamed into place. A
save killed at any moment leaves the old pair, the new pair, or a pending folder that the
next save, load or card read of NAME resolves (rolled forward if complete, else discarded).
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import platform
import zipfile
from datetime import UTC, datetime
from importlib import metadata
from pathlib import Path
from typing import Any

from rough_map._bounded import brief, clip
from rough_map._files import atomic_outputs
from rough_map.classify._checks import check_loaded_model
from rough_map.classify.model import MODEL_FORMAT, TerrainModel
from rough_map.classify.spectral import FEATURE_DOC, INPUT_SCALARS
from rough_map.config import jsonable
from rough_map.errors import FileFormatError, ModelError
from rough_map.io._model_archive import check_archive
from rough_map.io.model_files import (
    CARD_FORMAT,
    CARD_SUFFIX,
    MODEL_SUFFIX,
    model_paths,
    read_card,
    resolve_model,
    resolve_pending,
    sha256_file,
)
from rough_map.limits import LIMITS

log = logging.getLogger(__name__)

__all__ = [
    "CARD_SUFFIX",
    "MODEL_SUFFIX",
    "TRUSTED_TYPES",
    "build_card",
    "load_terrain_model",
    "model_paths",
    "read_card",
    "save_terrain_model",
    "sha256_file",
]

#: Types that skops does not trust by default and that a rough_map model file may hold,
#: named by the module that defines them (a file records that path). Anything else in a
#: file is refused.
TRUSTED_TYPES: tuple[str, ...] = (
    "rough_map.classify.model.TerrainModel",
    "rough_map.classify.novelty.ClassDistance",
    "rough_map.classify.spectral.SpectralFeatures",
    "rough_map.filter.defects.IsolatedSpikes",
    "rough_map.filter.path_filter.PathFilter",
    "sklearn.calibration._CalibratedClassifier",
    "sklearn.calibration._SigmoidCalibration",
    "sklearn.calibration._TemperatureScaling",
    "sklearn.ensemble._hist_gradient_boosting.predictor.TreePredictor",
    "sklearn.model_selection._split.PredefinedSplit",
    "sklearn.tree._tree.Tree",  # node arrays checked before use (classify._checks)
)

#: Libraries whose versions a card records.
_LIBRARIES = ("numpy", "scipy", "scikit-learn", "skops", "rough-map")


def _versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for lib in _LIBRARIES:
        try:
            out[lib] = metadata.version(lib)
        except metadata.PackageNotFoundError:
            out[lib] = "unknown"
    return out


def build_card(model: Any, model_file: Path, extra: dict[str, Any] | None = None) -> dict:
    """The model card of a fitted model already written to ``model_file``.

    Parameters
    ----------
    model : TerrainModel
        The fitted model.
    model_file : Path
        Its file (hashed here).
    extra : dict, optional
        More entries (e.g. the command that trained it).

    Returns
    -------
    dict
        JSON-ready card.
    """
    features = model.feature_names
    edges = model.classifier_.named_steps["features"].band_edges()

    def doc(name: str) -> str:
        if name.startswith("band_"):
            lo, hi = edges[int(name.split("_")[1])]
            return (
                f"mean log10 residual of the spectrum about its line over {lo:.0f}-{hi:.0f} rad/m"
            )
        return FEATURE_DOC.get(name, "")

    card = {
        "format": CARD_FORMAT,
        "model_file": model_file.name,
        "sha256": sha256_file(model_file),
        "size_bytes": model_file.stat().st_size,
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "model_format": model.format_,
        "classes": [str(c) for c in model.classes_],
        "features": {
            "inputs": [*INPUT_SCALARS, f"log10 PSD at {len(model.omega_)} wavenumbers"],
            "omega_rad_per_m": [float(model.omega_[0]), float(model.omega_[-1])],
            "derived": {name: doc(name) for name in features},
        },
        "classifier": {
            "kind": model.kind,
            "pipeline": [name for name, _ in model.classifier_.steps],
            "class_weight": "balanced",
            "calibration": "temperature scaling, folds of whole traverses",
            "level_jitter_log10": float(model.level_jitter),
            "waviness_jitter": float(model.waviness_jitter),
        },
        "filter": _filter_card(model),
        "novelty": None if getattr(model, "novelty_", None) is None else model.novelty_.summary(),
        "roughness_levels": {
            "levels": list(model.level_names_),
            "thresholds_m3_per_rad": list(model.level_thresholds_),
            "quantity": "R = Phi(1 rad/m), m^3/rad",
        },
        "feature_extraction": model.extraction_,
        "training_data": model.training_,
        "cross_validation": model.cv_report_,
        "versions": _versions(),
    }
    if extra:
        card.update(extra)
    return jsonable(card)  # NaN (e.g. an undefined CV score) becomes null


def _filter_card(model: Any) -> dict[str, Any]:
    """The card's description of the path filter and the defect detector."""
    flt = model.filter_
    card: dict[str, Any] = {
        "mode": model.mode,
        "evidence_per_m": None if flt is None else float(model.evidence_per_m_),
        "emission": "min(1, evidence_per_m * step_m) * log p(class | frame)",
        "defect_ratio": getattr(model.defects, "ratio", None),
    }
    if flt is None:
        card["emission"] = None  # no path filter: the filtered class is the raw one
        return card
    card["switch_rate_per_m"] = {
        str(c): float(-flt.generator_[i, i]) for i, c in enumerate(flt.classes_)
    }
    card["class_prior"] = {
        str(c): float(p) for c, p in zip(flt.classes_, flt.class_prior_, strict=True)
    }
    return card


def save_terrain_model(
    model: Any, name: str | Path, *, card_extra: dict[str, Any] | None = None
) -> tuple[Path, Path]:
    """Write a fitted model and its card.

    Parameters
    ----------
    model : TerrainModel
        Fitted.
    name : str or Path
        ``models/NAME`` (suffixes are added; see :func:`model_paths`).
    card_extra : dict, optional
        More card entries.

    Returns
    -------
    (Path, Path)
        The model file and the card.

    Raises
    ------
    ModelError
        The model is not a fitted TerrainModel.
    """
    import skops.io as sio

    if not isinstance(model, TerrainModel) or not hasattr(model, "classifier_"):
        raise ModelError(f"only a fitted TerrainModel can be saved; got {type(model).__name__}")
    model_file, card_file = model_paths(name)
    try:
        model_file.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ModelError(f"{model_file.parent}: cannot create the folder ({brief(err)})") from err
    card: dict[str, Any] = {}

    def write_model(path: Path) -> None:
        sio.dump(model, path, compression=zipfile.ZIP_DEFLATED, compresslevel=9)

    def write_card(path: Path) -> None:
        card.update(build_card(model, path.with_name(model_file.name), card_extra))
        path.write_text(json.dumps(card, indent=2) + "\n", encoding="utf-8")

    # one set: a new model never sits beside an old card (rough_map._files.atomic_outputs)
    try:
        resolve_pending(model_file, card_file)
        with atomic_outputs([model_file, card_file]) as (model_tmp, card_tmp):
            write_model(model_tmp)
            write_card(card_tmp)  # hashes the staged model beside it, under its final name
    except FileFormatError as err:
        raise ModelError(str(err)) from None
    except OSError as err:
        raise ModelError(f"{model_file}: cannot write the model ({brief(err)})") from err
    log.info("wrote %s (%d bytes) and %s", model_file, card["size_bytes"], card_file)
    return model_file, card_file


def load_terrain_model(name: str | Path, *, verify: bool = True) -> Any:
    """Load a model written by :func:`save_terrain_model`, safely.

    Parameters
    ----------
    name : str or Path
        ``models/NAME`` or ``models/NAME.skops`` (a path), or the bare name of a model
        shipped with rough_map (``default``) when no such file exists.
    verify : bool
        Check the file's sha256 against its card (a missing card is then an error). With
        ``verify=False`` a missing card only logs a warning; a card that disagrees with the
        file is an error either way.

    Returns
    -------
    TerrainModel

    Raises
    ------
    ModelError
        No such file; not a skops file; types outside the trusted ones; a sha256 that
        differs from the card's; an object other than a TerrainModel of this format.
    """
    import skops.io as sio
    from skops.io.exceptions import UntrustedTypesFoundException

    model_file, card_file = resolve_model(name)
    resolve_pending(model_file, card_file)
    try:
        size = model_file.stat().st_size
        if size > LIMITS.model_file:
            raise ModelError(
                f"{model_file}: {size} bytes; a model file has at most {LIMITS.model_file}"
            )
        data = model_file.read_bytes()
    except OSError as err:
        raise ModelError(f"{model_file}: cannot read the model ({brief(err)})") from err
    digest = hashlib.sha256(data).hexdigest()
    if card_file.is_file():
        expected = read_card(card_file)["sha256"]
        if expected != digest:
            raise ModelError(
                f"{model_file}: sha256 {digest[:16]}... is not the {clip(expected, 19)} of "
                f"{card_file.name}: altered or replaced since it was written; refusing to load it"
            )
    elif verify:
        raise ModelError(
            f"{model_file}: no model card {card_file.name} next to it, so its sha256 cannot be "
            "checked (load with verify=False to skip the check)"
        )
    else:
        log.warning("%s: no model card; the file's integrity is not checked", model_file)
    check_archive(data, model_file)
    try:
        untrusted = sio.get_untrusted_types(data=data)
    except Exception as err:  # whatever skops raises on a malformed schema
        raise ModelError(f"{model_file}: not a skops model file ({brief(err)})") from None
    refused = sorted(set(untrusted) - set(TRUSTED_TYPES))
    if refused:
        names = ", ".join(repr(t)[:60] for t in refused[:3]) + (", ..." if len(refused) > 3 else "")
        raise ModelError(
            f"{model_file}: refusing to load types rough_map does not trust: {names}; the "
            "file was not written by this version of rough_map, or it was altered"
        )
    try:
        model = sio.load(io.BytesIO(data), trusted=list(TRUSTED_TYPES))
    except UntrustedTypesFoundException as err:
        raise ModelError(
            f"{model_file}: refusing to load types rough_map does not trust ({brief(err, 120)})"
        ) from None
    except Exception as err:  # BadZipFile, zlib.error, TokenError, ...
        raise ModelError(f"{model_file}: cannot load the model ({brief(err)})") from None
    if not isinstance(model, TerrainModel):
        raise ModelError(
            f"{model_file}: holds a {type(model).__module__:.40}.{type(model).__name__:.40}, "
            "not a rough_map TerrainModel"
        )
    if getattr(model, "format_", None) != MODEL_FORMAT:
        raise ModelError(
            f"{model_file}: model format {getattr(model, 'format_', None)!r:.40}; this version "
            f"of rough_map reads {MODEL_FORMAT!r}; retrain it with `rough-map train`"
        )
    check_loaded_model(model, model_file)
    return model
