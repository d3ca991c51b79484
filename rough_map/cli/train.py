"""``rough-map train TRAVERSE... --out NAME``: fit a terrain model and write its card.

For every traverse the features of the patch ahead are computed from its clouds (or read
from a features table written by ``rough-map features``); the classifier is
cross-validated with whole traverses as folds (GroupKFold; with one traverse, contiguous
blocks of frames, which the card says), fitted on all frames, and the path filter is fitted
on the held-out posteriors. ``models/NAME.skops`` and ``models/NAME.card.json`` are written.

Reproducing ``models/default.skops``
------------------------------------
Six 100 m ``random`` courses (all five surfaces in 8-25 m segments), at the paper's speeds
of 0.3, 0.5 and 0.7 m/s and with range sensors of different density and noise, so that the
model does not learn one sensor::

    rough-map simulate --out sim/train-101 --course random --length 100 --seed 101 --speed 0.3 --points-per-cell 12 --noise 0.0005 --no-images
    rough-map simulate --out sim/train-102 --course random --length 100 --seed 102 --speed 0.5 --points-per-cell 12 --noise 0.0005 --no-images
    rough-map simulate --out sim/train-103 --course random --length 100 --seed 103 --speed 0.7 --points-per-cell 6 --noise 0.001 --no-images
    rough-map simulate --out sim/train-104 --course random --length 100 --seed 104 --speed 0.3 --points-per-cell 20 --noise 0.0003 --no-images
    rough-map simulate --out sim/train-105 --course random --length 100 --seed 105 --speed 0.5 --points-per-cell 8 --noise 0.0015 --no-images
    rough-map simulate --out sim/train-106 --course random --length 100 --seed 106 --speed 0.7 --points-per-cell 12 --noise 0.0005 --no-images
    rough-map train sim/train-101 sim/train-102 sim/train-103 sim/train-104 sim/train-105 sim/train-106 --out models/default

(about 12 min on a quiet 2-core machine: 10 to simulate, 2 to compute the features and
fit; the traverses take 9.4 GB of clouds, less with ``simulate --compress``, which the
shipped model's were made with). The card records the sha256 of the training features:
the shipped model was fitted on data with ``b6de8ab0...``, this version's simulator (courses
longer than 50 m built in 6 m tiles) and feature extraction (cell means at any density, the
noise floor of issue 12). Any later change to the simulator or the feature extraction gives
other traverses, another hash and another model.

``train`` also fits the model's novelty score (:mod:`rough_map.classify.novelty`). The
shipped model was trained before the score existed, so it got its score from the same six
traverses simulated again and read with this version's feature extraction (sha256
``66459d40...``, the card's ``novelty`` entry), its classifier left as it was::

    for s in 101 102 103 104 105 106; do rough-map features sim/train-$s --out feat-$s.csv; done
    python tools/fit_novelty.py models/default feat-101.csv feat-102.csv feat-103.csv feat-104.csv feat-105.csv feat-106.csv
"""  # noqa: E501

from __future__ import annotations

import argparse
from pathlib import Path

from rough_map.cli._common import (
    add_jobs_arg,
    add_patch_args,
    add_traverses_arg,
    emit_json,
    existing_path,
    int_at_least,
    open_traverses,
    patch_spec,
    status,
    table,
)
from rough_map.errors import InputError
from rough_map.patch import Extraction

#: rough_map.classify.CLASSIFIERS, spelled out so that the parser does not import sklearn.
CLASSIFIERS = ("logistic", "hgb", "forest")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "train",
        help="train a terrain classifier and path filter on labelled traverses",
        description=(
            "Compute the PSD features of every frame of the labelled traverses, cross-"
            "validate the classifier with whole traverses as folds, fit it and the path "
            "filter, and write models/NAME.skops with its card models/NAME.card.json "
            "(classes, features, training-data hash, cross-validated metrics, versions, "
            "sha256 of the model file). A TRAVERSE may also be a features table (.csv) "
            "written by `rough-map features`."
        ),
    )
    add_traverses_arg(p, many=True)
    p.add_argument(
        "--out",
        type=Path,
        required=True,
        metavar="NAME|PATH",
        help="the model: a bare NAME goes to the user models folder ($ROUGH_MAP_MODELS, "
        "default ~/.local/share/rough_map/models) and is then used as --model NAME; a "
        "path (dir/NAME) writes dir/NAME.skops and dir/NAME.card.json",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace a model already at --out (a trained model is never replaced silently)",
    )
    p.add_argument(
        "--classifier",
        choices=CLASSIFIERS,
        default=CLASSIFIERS[0],
        help="base classifier (default logistic: multinomial logistic regression)",
    )
    p.add_argument(
        "--mode",
        choices=("forward", "smooth", "viterbi"),
        default="smooth",
        help="default filter mode of classify/evaluate/map (default smooth)",
    )
    p.add_argument(
        "--levels",
        type=existing_path,
        metavar="FILE",
        help="roughness levels like configs/roughness_levels.yaml (default: built in)",
    )
    p.add_argument(
        "--cv",
        type=int_at_least(2),
        default=5,
        metavar="K",
        help="cross-validation folds of whole traverses (default 5)",
    )
    p.add_argument("--no-tilt", action="store_true", help="ignore the IMU roll/pitch of the frames")
    p.add_argument(
        "--save-features",
        type=Path,
        metavar="DIR",
        help="also write each traverse's features table to DIR/NAME.csv (and its metadata "
        "to DIR/NAME.csv.json)",
    )
    add_patch_args(p)
    add_jobs_arg(p)
    p.add_argument("--json", action="store_true", help="print the model card as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # rough_map.classify and rough_map.filter import scikit-learn: only when training
    from rough_map.classify import load_roughness_levels, read_card, save_terrain_model
    from rough_map.features import feature_tables, write_features
    from rough_map.filter import make_terrain_model

    args.out = model_target(args.out)
    _check_new_model(args.out, args.force)
    levels = load_roughness_levels(args.levels)
    _check_labelled(args.traverses)
    extraction = Extraction(patch=patch_spec(args), use_imu=not args.no_tilt).to_dict()
    sources = open_traverses(args, args.traverses)
    tables = feature_tables(sources, extraction, n_jobs=args.jobs, progress=args.progress)
    if args.save_features is not None:
        from rough_map._files import output_set

        # a set: staged beside the folder and swapped in whole; other files there are kept
        with output_set(args.save_features) as stage:
            for src, tab in zip(args.traverses, tables, strict=True):
                if src.suffix.lower() not in (".csv", ".parquet"):
                    write_features(tab, stage / f"{tab.name or src.name}.csv")
    model = make_terrain_model(
        kind=args.classifier,
        mode=args.mode,
        level_names=levels.levels,
        level_thresholds=tuple(float(v) for v in levels.values()),
        cv=args.cv,
        extraction=extraction,
    ).fit(tables)
    model_file, card_file = save_terrain_model(
        model, args.out, card_extra={"command": getattr(args, "command_line", None)}
    )
    card = read_card(card_file)
    status(args, f"wrote {model_file} and {card_file}")
    if args.json:
        emit_json(card)
        return 0
    cv = card["cross_validation"]
    rows = [
        [
            "model",
            f"{model_file} ({card['size_bytes'] / 1e6:.2f} MB, sha256 {card['sha256'][:16]}...)",
        ],
        ["classes", ", ".join(card["classes"])],
        [
            "training",
            f"{len(tables)} traverses, {sum(len(t) for t in tables)} frames, "
            f"data sha256 {card['training_data']['sha256'][:16]}...",
        ],
        ["cross-validation", cv["scheme"]],
        ["raw", f"macro-F1 {cv['raw']['macro_f1']:.3f}, accuracy {cv['raw']['accuracy']:.3f}"],
        [
            "filtered",
            f"macro-F1 {cv['filtered']['macro_f1']:.3f}, accuracy "
            f"{cv['filtered']['accuracy']:.3f} ({cv['mode']})",
        ],
    ]
    print(table(rows))
    return 0


def _check_labelled(sources: list[Path]) -> None:
    """Refuse traverses without any label before spending time on their features."""
    from rough_map.io.traverse import load_traverse

    for src in sources:
        if src.is_file() and src.suffix.lower() in (".csv", ".parquet"):
            continue  # a features table: checked when the model is fitted
        traverse = load_traverse(src)
        if not any(traverse.labels()):
            raise InputError(
                f"traverse {traverse.name!r} ({src}) has no labelled frames; training needs a "
                "terrain class ('label') on the frames"
            )


def model_target(out: Path) -> Path:
    """Where ``train --out`` writes: a bare name in the user models folder, a path as it
    is; never a model of the user's in the package's ``models/`` (which holds the shipped
    ones, retrained with their own names)."""
    from rough_map.resources import SHIPPED_MODELS, in_package_models, user_models_dir

    text = str(out)
    if out.name == text and not text.endswith((".skops", ".card.json")):
        folder = user_models_dir()
        folder.mkdir(parents=True, exist_ok=True)
        return folder / text
    name = out.name.removesuffix(".skops").removesuffix(".card.json")
    if in_package_models(out) and name not in SHIPPED_MODELS:
        raise InputError(
            f"{out.name}: models/ holds only the shipped models ({', '.join(SHIPPED_MODELS)}); "
            f"train yours by name (--out {name}: into the user models folder) or to a path"
        )
    return out


def _check_new_model(out: Path, force: bool) -> None:
    """Refuse, before any work, to replace a model at ``out`` without ``--force``."""
    from rough_map.io.model_files import model_paths

    there = [p for p in model_paths(out) if p.exists()]
    if there and not force:
        raise InputError(
            f"{there[0]} exists: train does not replace a model without --force "
            "(or choose another --out)"
        )
