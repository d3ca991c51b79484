#!/usr/bin/env python3
"""Give a trained terrain model its novelty score, leaving its classifier and filter as they are.

    python tools/fit_novelty.py models/default FEATURES.csv [FEATURES.csv ...]

``rough-map train`` fits the score (:mod:`rough_map.classify.novelty`) with every model. A
model trained before it has none: this fits it on labelled features tables of the training
traverses (``rough-map features TRAVERSE --out FEATURES.csv``), with the threshold from the
model's own folds of whole traverses, and writes the model and its card again as one set.
The card's ``novelty`` entry records the sha256 of the tables it was fitted on
(:func:`rough_map.classify.training.training_hash`), and ``command`` keeps the command
that trained the model.

The shipped ``models/default`` got its score this way, from the six training traverses of
``rough_map/cli/train.py``'s recipe computed with this version's feature extraction.

Exit status: 0 written; 2 a bad model, table or argument (one line on stderr).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from rough_map.classify import load_terrain_model, read_card, save_terrain_model
from rough_map.classify.model import fit_novelty
from rough_map.classify.training import TrainingFrames, training_hash, traverse_folds
from rough_map.errors import RoughMapError
from rough_map.features import read_features


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("model", type=Path, help="the model, as models/NAME")
    p.add_argument("features", type=Path, nargs="+", help="labelled features tables")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        model = load_terrain_model(args.model)
        card = read_card(args.model)
        tables = [read_features(f) for f in args.features]
        frames = TrainingFrames.from_tables(tables)
        folds = traverse_folds(frames.traverse, model.cv)
        model.novelty_ = fit_novelty(
            model.classifier_, frames.X, frames.y, frames.valid, folds.splits
        )
        novelty = {
            **model.novelty_.summary(),
            "training_sha256": training_hash(tables),
            "fitted_by": "tools/fit_novelty.py, on the tables of this hash",
        }
        extra = {"command": card.get("command"), "novelty": novelty}
        save_terrain_model(model, args.model, card_extra=extra)
    except RoughMapError as err:
        print(f"fit_novelty: {err}", file=sys.stderr)
        return 2
    print(f"{args.model}: novelty threshold {model.novelty_.threshold_:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
