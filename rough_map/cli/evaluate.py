"""``rough-map evaluate TRAVERSE... --model M``: how well a model labels traverses.

Scores the raw (per-frame classifier) and the filtered classes against the traverses'
labels (:func:`rough_map.evaluation.evaluate_model`): confusion matrix (counts and
row-normalised), precision, recall and F1 per class, macro-F1 and accuracy, all computed by
:mod:`sklearn.metrics` on the scored frames.

Scored frames are the frames with a label and a valid patch, the same set for raw and
filtered, so the two are comparable and each number equals the ``sklearn.metrics`` call on
the labels of those frames. Frames without a label are skipped; frames without a valid
patch have no raw class (the filter still predicts them from its neighbours) and are
skipped too. Both counts are reported. Labels the model does not know are an error.

Raw and filtered share one list of classes (every class true or predicted on a scored
frame, sorted). The macro-F1 is the mean F1 over the classes present in the labels
(``scored_classes``); a class that is predicted but never true is listed with its precision
but not averaged.

``--json`` prints one object with ``raw`` and ``filtered``, each holding ``classes``,
``confusion_matrix``, ``confusion_matrix_normalized``, ``precision``, ``recall``, ``f1``,
``support``, ``accuracy``, ``macro_f1`` and ``scored_classes``, plus ``scored_classes``,
the frame counts and per-traverse results.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from rough_map.cli._common import (
    add_jobs_arg,
    add_mode_arg,
    add_model_arg,
    add_traverses_arg,
    chosen_model,
    emit_json,
    open_traverses,
    status,
    table,
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "evaluate",
        help="confusion matrix, precision/recall/F1, macro-F1 and accuracy, raw and filtered",
        description=(
            "Classify labelled traverses with a model from `rough-map train` and score the "
            "raw and the filtered classes against the labels (frames with a label and a "
            "valid patch). Unlabelled frames and frames without a valid patch are counted "
            "and skipped."
        ),
    )
    add_traverses_arg(p, many=True)
    add_model_arg(p)
    add_mode_arg(p)
    add_jobs_arg(p)
    p.add_argument("--json", action="store_true", help="print the results as JSON")
    p.add_argument(
        "--plot",
        type=Path,
        metavar="cm.png",
        help="draw the row-normalised confusion matrices (raw and filtered)",
    )
    p.set_defaults(func=run)


def _report(part: dict[str, Any], title: str) -> str:
    names = part["classes"]
    cm = part["confusion_matrix"]
    norm = part["confusion_matrix_normalized"]
    head = ["true \\ predicted", *names]
    counts = table([[n, *(str(v) for v in row)] for n, row in zip(names, cm, strict=True)], head)
    fracs = table(
        [[n, *(f"{v:.2f}" for v in row)] for n, row in zip(names, norm, strict=True)], head
    )
    scored = part.get("scored_classes", names)
    per = table(
        [
            [
                n,
                f"{part['precision'][n]:.3f}",
                f"{part['recall'][n]:.3f}",
                f"{part['f1'][n]:.3f}",
                str(part["support"][n]),
                "yes" if n in scored else "no (never true)",
            ]
            for n in names
        ],
        ["class", "precision", "recall", "F1", "support", "in macro-F1"],
    )
    return (
        f"== {title}: macro-F1 {part['macro_f1']:.3f} over the {len(scored)} true classes "
        f"({', '.join(scored)}), accuracy {part['accuracy']:.3f} "
        f"({part['frames']} frames)\n\nconfusion matrix (counts)\n{counts}\n\n"
        f"confusion matrix (row-normalised)\n{fracs}\n\n{per}\n"
    )


def run(args: argparse.Namespace) -> int:
    # rough_map.classify imports scikit-learn and skops: only when evaluating
    from rough_map.classify import load_terrain_model
    from rough_map.evaluation import evaluate_model
    from rough_map.features import feature_tables

    model = load_terrain_model(chosen_model(args))
    tables = feature_tables(
        open_traverses(args, args.traverses),
        model.reading(),
        n_jobs=args.jobs,
        progress=args.progress,
    )
    result = evaluate_model(model, tables, args.mode)
    result["model"] = "default" if args.model is None else str(args.model)
    fr = result["frames"]
    status(
        args,
        f"scored {fr['scored']} of {fr['total']} frames; skipped {fr['unlabelled']} without "
        f"a label and {fr['invalid']} without a valid patch",
    )
    if args.plot is not None:
        from rough_map.export.figures import confusion_matrices  # matplotlib: only to draw

        confusion_matrices(result, args.plot)
        status(args, f"wrote {args.plot}")
    if args.json:
        emit_json(result)
        return 0
    print(_report(result["raw"], "raw"))
    print(_report(result["filtered"], f"filtered ({result['mode']})"))
    if len(result["per_traverse"]) > 1:
        print(
            table(
                [
                    [
                        t["name"],
                        str(t["frames"]),
                        f"{t['raw']['macro_f1']:.3f}",
                        f"{t['filtered']['macro_f1']:.3f}",
                    ]
                    for t in result["per_traverse"]
                ],
                ["traverse", "frames", "raw macro-F1", "filtered macro-F1"],
            )
        )
    return 0
