"""Helpers shared by the command modules: argument groups and output."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from rough_map.patch import DEFAULT_AHEAD, DEFAULT_SIZE, DEFAULT_SPACING, PatchSpec


def add_traverses_arg(parser: argparse.ArgumentParser, *, many: bool = False) -> None:
    """The positional TRAVERSE (or TRAVERSE... with ``many``): folder, file or table."""
    parser.add_argument(
        "traverses" if many else "traverse",
        nargs="+" if many else None,
        type=Path,
        metavar="TRAVERSE",
        help=("labelled " if many else "") + "traverse folder or file, or a features table (.csv)",
    )


def add_model_arg(parser: argparse.ArgumentParser, *, required: bool = True) -> None:
    """``--model M``: a model from ``rough-map train`` (optional: the shipped default)."""
    parser.add_argument(
        "--model",
        type=Path,
        required=required,
        default=None,
        metavar="M",
        help="model name or file (models/NAME or models/NAME.skops)"
        + ("" if required else "; default models/default shipped with rough_map"),
    )


def add_mode_arg(parser: argparse.ArgumentParser, default: str | None = None) -> None:
    """``--mode``: the path filter's mode."""
    parser.add_argument(
        "--mode",
        choices=("forward", "smooth", "viterbi"),
        default=default,
        help="filter mode (default: "
        + (default or "the model's")
        + "; forward is online, smooth and viterbi use the whole traverse)",
    )


def add_patch_args(parser: argparse.ArgumentParser) -> None:
    """--spacing/--size/--ahead/--lateral, all in metres."""
    g = parser.add_argument_group("patch of interest (vehicle frame, metres)")
    g.add_argument(
        "--spacing",
        type=float,
        default=DEFAULT_SPACING,
        metavar="M",
        help=f"grid step B in m (default {DEFAULT_SPACING})",
    )
    g.add_argument(
        "--size",
        type=float,
        default=DEFAULT_SIZE,
        metavar="M",
        help=f"side of the square patch in m (default {DEFAULT_SIZE})",
    )
    g.add_argument(
        "--ahead",
        type=float,
        default=DEFAULT_AHEAD,
        metavar="M",
        help=f"distance of the patch centre ahead of the vehicle in m (default {DEFAULT_AHEAD})",
    )
    g.add_argument(
        "--lateral",
        type=float,
        default=0.0,
        metavar="M",
        help="offset of the patch centre to the left in m (default 0)",
    )


def add_psd_args(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("estimator")
    g.add_argument(
        "--method",
        choices=("unbiased", "paper"),
        default="unbiased",
        help="'unbiased' corrects the log-periodogram bias (default); 'paper' is "
        "the paper's plain log-log fit (R about 44%% low)",
    )
    g.add_argument(
        "--keep-noise",
        action="store_true",
        help="do not subtract the noise floor estimated from the within-cell scatter",
    )


def patch_spec(args: argparse.Namespace) -> PatchSpec:
    return PatchSpec(ahead=args.ahead, size=args.size, spacing=args.spacing, lateral=args.lateral)


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    return value


def emit_json(obj: Any) -> None:
    """One JSON document on stdout (NaN and inf become null)."""
    json.dump(_jsonable(obj), sys.stdout, indent=None, separators=(",", ": "))
    sys.stdout.write("\n")


def table(rows: list[list[str]], header: list[str] | None = None) -> str:
    """A plain aligned text table."""
    allrows = ([header] if header else []) + rows
    widths = [max(len(r[i]) for r in allrows) for i in range(len(allrows[0]))]
    lines = [
        "  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in allrows
    ]
    if header:
        lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)
