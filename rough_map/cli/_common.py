"""Helpers shared by the command modules: the parser, argument types and groups, output.

Conventions every command keeps (``rough_map.cli.main`` builds the sub-parsers with
:class:`CommandParser`):

* ``-q``/``-v`` work before and after the command name;
* a bad argument is one line on stderr, ``rough-map CMD: error: ...``, and exit status 2;
* every option has help text, which shows its default;
* numbers are checked by the type functions below (:func:`positive_float` ...), paths that
  must exist by :func:`existing_path`;
* data goes to stdout; status lines go to stderr through :func:`status`, which ``-q``
  silences; progress bars only when stderr is a terminal.
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import re
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, NoReturn

from rough_map.errors import InputError
from rough_map.patch import DEFAULT_AHEAD, DEFAULT_SIZE, DEFAULT_SPACING, PatchSpec

# --------------------------------------------------------------------------- the parser


class DefaultsHelpFormatter(argparse.HelpFormatter):
    """Appends ``(default: X)`` to an option's help unless the help already names X.

    Defaults of None and False (an option not given, a flag not set) are not shown.
    """

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        default = action.default
        if (
            text
            and action.option_strings
            and not (default is None or default is False or default == argparse.SUPPRESS)
            and "%(default)" not in text
            and not mentions_default(text, default)
        ):
            text += " (default: %(default)s)"
        return text


def mentions_default(text: str, default: Any) -> bool:
    """Whether a help text already says its default, e.g. "(default 0.1)"."""
    text = text.replace("%%", "%")
    return "default" in text and str(default) in text


def _with_defaults(formatter: type[argparse.HelpFormatter]) -> type[argparse.HelpFormatter]:
    if issubclass(formatter, DefaultsHelpFormatter):
        return formatter
    return type(f"Defaults{formatter.__name__}", (DefaultsHelpFormatter, formatter), {})


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line (no usage block) and whose help shows
    the defaults."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs["formatter_class"] = _with_defaults(
            kwargs.get("formatter_class", argparse.HelpFormatter)
        )
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> NoReturn:
        self.exit(2, error_line(self.prog, message) + "\n")


def add_command(
    sub: argparse._SubParsersAction, name: str, help: str, doc: str | None, **kwargs: Any
) -> argparse.ArgumentParser:
    """The parser of command ``name``: ``help`` is its line in ``rough-map --help``, and
    its description is its module's docstring after the first paragraph (the usage line).
    """
    description = doc.split("\n\n", 1)[1] if doc and "\n\n" in doc else None
    parser: argparse.ArgumentParser = sub.add_parser(
        name, help=help, description=description, **kwargs
    )
    return parser


def add_verbosity_args(parser: argparse.ArgumentParser, *, suppress: bool = False) -> None:
    """``-v``/``-q``. A command's parser takes them with ``suppress=True``
    (``default=argparse.SUPPRESS``): an option given before the command name is then not
    reset by the command parser's default."""
    parser.add_argument(
        "-v",
        "--verbose",
        action="count",
        default=argparse.SUPPRESS if suppress else 0,
        help="more log output on stderr: -v info, -vv debug",
    )
    parser.add_argument(
        "-q",
        "--quiet",
        action="store_true",
        default=argparse.SUPPRESS if suppress else False,
        help="only errors on stderr: no status lines, warnings or progress bars",
    )


class CommandParser(Parser):
    """The parser of one command: :class:`Parser` plus ``-v``/``-q``."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        add_verbosity_args(self, suppress=True)


#: Longest error message the CLI prints after ``rough-map CMD: error: ``; a longer one is
#: shortened in the middle, keeping its start (the file name) and its end.
MAX_ERROR_MESSAGE = 200


def printable(text: str) -> str:
    """``text`` on one line: line breaks become one space, other characters that are not
    printable (control bytes, surrogates of undecodable file names) are escaped
    (``\\x00``, ``\\udcff``)."""
    text = re.sub(r"\s*[\r\n]+\s*", " ", text.strip())
    if text.isprintable():
        return text
    return "".join(
        c if c.isprintable() else " " if c == "\t" else c.encode("unicode_escape").decode("ascii")
        for c in text
    )


def error_line(prog: str, message: str, *, kind: str = "error", suffix: str = "") -> str:
    """The one printable line of a failure, ``PROG: KIND: MESSAGE[SUFFIX]``, where
    ``MESSAGE[SUFFIX]`` is at most :data:`MAX_ERROR_MESSAGE` characters."""
    from rough_map._bounded import shorten  # on a failure only: _bounded imports yaml

    room = max(60, MAX_ERROR_MESSAGE - len(suffix))
    return f"{printable(prog)}: {kind}: " + shorten(printable(message), room) + suffix


def status(args: argparse.Namespace, message: str) -> None:
    """A status line for the user on stderr ("wrote 48 frames to ..."), unless ``-q``."""
    if not getattr(args, "quiet", False):
        print(message, file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- argument types

#: How units read in the messages of the type functions.
_UNIT_NAMES = {
    "m": "metres",
    "m/s": "metres per second",
    "Hz": "hertz",
    "deg": "degrees",
    "px": "pixels",
    "": "",
}


@contextmanager
def unused_optional_imports(*names: str) -> Iterator[None]:
    """Import within the block as if the packages ``names`` were not installed, unless
    something already imported them; afterwards they import normally again.

    scikit-learn imports pandas (and with it pyarrow) whenever it is installed, though
    rough_map hands it numpy arrays only: in an environment that has pandas, that is 63 MB
    and 0.2 s of a `rough-map map` process, a seventh of its memory budget. scikit-learn
    works without pandas (it then only refuses DataFrames, which rough_map never gives it).
    Likewise dask, which its array-library checks import during a prediction. Only the
    imports are blocked: the block must not be held over code that looks a package up in
    ``sys.modules`` (scikit-learn's predictions do, for pandas).
    """
    blocked = [n for n in names if n not in sys.modules]
    for name in blocked:
        sys.modules[name] = None  # type: ignore[assignment]  # import raises ImportError
    try:
        yield
    finally:
        for name in blocked:
            if name in sys.modules and sys.modules[name] is None:
                del sys.modules[name]


@contextmanager
def start_up() -> Iterator[None]:
    """Run a command's start-up (its imports, the traverse's frame list) without the
    cyclic garbage collector, then freeze what it built (:func:`gc.freeze`).

    Imports leave little cyclic garbage, but each automatic full collection walks every
    object already made: the ~200,000 of scikit-learn, scipy and matplotlib's modules. In
    `rough-map map` on an hour of driving the main process spent 0.7-0.8 s collecting,
    0.5-0.6 s of it in six full collections, four of them during the imports; with this,
    0.3 s. Frozen objects are never walked again; reference counting still frees them.
    """
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        gc.freeze()
        if enabled:
            gc.enable()


def _number(text: str, kind: type) -> float | int:
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected {'a whole number' if kind is int else 'a number'}, got {text!r}"
        ) from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def _noun(kind: type, unit: str) -> str:
    units = _UNIT_NAMES.get(unit, unit)
    return ("whole number" if kind is int else "number") + (f" of {units}" if units else "")


def _checked(kind: type, test: Callable[[Any], bool], expected: str, name: str) -> Callable:
    def parse(text: str) -> Any:
        value = _number(text, kind)
        if not test(value):
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
        return value

    parse.__name__ = name  # argparse names the type in some messages
    return parse


def positive_float(unit: str = "m") -> Callable[[str], float]:
    """Argument type: a finite float > 0, e.g. ``type=positive_float("m")``."""
    return _checked(float, lambda v: v > 0, f"a positive {_noun(float, unit)}", "positive")


def non_negative_float(unit: str = "m") -> Callable[[str], float]:
    """Argument type: a finite float >= 0."""
    return _checked(float, lambda v: v >= 0, f"a non-negative {_noun(float, unit)}", "non-negative")


def finite_float(unit: str = "m") -> Callable[[str], float]:
    """Argument type: any finite float (an offset, an angle)."""
    return _checked(float, lambda v: True, f"a finite {_noun(float, unit)}", "finite")


def positive_int(unit: str = "") -> Callable[[str], int]:
    """Argument type: a whole number >= 1."""
    return _checked(int, lambda v: v >= 1, f"a positive {_noun(int, unit)}", "positive")


def non_negative_int(unit: str = "") -> Callable[[str], int]:
    """Argument type: a whole number >= 0 (a seed)."""
    return _checked(int, lambda v: v >= 0, f"a non-negative {_noun(int, unit)}", "non-negative")


def int_at_least(minimum: int, unit: str = "") -> Callable[[str], int]:
    """Argument type: a whole number >= ``minimum``."""
    return _checked(int, lambda v: v >= minimum, f"a {_noun(int, unit)} >= {minimum}", "int")


def xy_metres(text: str) -> tuple[float, float]:
    """Argument type: ``X,Y`` in m."""
    parts = text.split(",")
    try:
        x, y = (finite_float("m")(p) for p in parts)
    except (ValueError, argparse.ArgumentTypeError):
        raise argparse.ArgumentTypeError(f"expected X,Y in m, got {text!r}") from None
    return x, y


def add_vehicle_args(parser: argparse.ArgumentParser) -> None:
    """``--vehicle NAME|FILE`` and ``--speed M/S``: the speed advice for a vehicle."""
    g = parser.add_argument_group("speed advice for a vehicle (rough_map.vehicle)")
    g.add_argument(
        "--vehicle",
        metavar="NAME|FILE",
        help="a preset (rover, tractor, car) or a vehicle file: adds v_max and v_max_95 "
        "(m/s, the highest speed keeping its limits; with 95 %% confidence)",
    )
    g.add_argument(
        "--speed",
        type=positive_float("m/s"),
        metavar="M/S",
        help="with --vehicle: also the rms responses at this speed (weighted acceleration, "
        "suspension travel, dynamic load ratio)",
    )


def chosen_vehicle(args: argparse.Namespace) -> Any:
    """The :class:`rough_map.vehicle.Vehicle` of ``--vehicle`` (None without one).

    Raises
    ------
    InputError
        ``--speed`` without ``--vehicle``, or above its top speed.
    """
    if args.vehicle is None:
        if args.speed is not None:
            raise InputError("--speed gives the responses of a --vehicle: name one")
        return None
    from rough_map.vehicle import load_vehicle

    vehicle = load_vehicle(args.vehicle)
    top = vehicle.limits.top_speed
    if args.speed is not None and args.speed > top:
        raise InputError(f"--speed {args.speed:g} m/s is above the {vehicle.name}'s {top:g} m/s")
    return vehicle


def add_costmap_args(parser: argparse.ArgumentParser) -> None:
    """The costmap's settings (with ``--vehicle``): lethal speed and classes, mode."""
    g = parser.add_argument_group("the costmap written with --vehicle (map_costmap.pgm/.yaml)")
    g.add_argument(
        "--lethal-speed",
        type=non_negative_float("m/s"),
        default=0.0,
        metavar="M/S",
        help="cells whose v_max is at or below this are lethal (default 0.0 m/s)",
    )
    g.add_argument(
        "--lethal-class",
        action="append",
        metavar="CLASS",
        help="a terrain class that is lethal whatever its roughness (repeat for more)",
    )
    g.add_argument(
        "--costmap-mode",
        choices=("raw", "trinary"),
        default="raw",
        help="map_server mode of the image: raw (pixel = cost 0-100, 255 unknown; the "
        "default) or trinary (occupied, free, unknown by the YAML's thresholds)",
    )


def costmap_settings(args: argparse.Namespace) -> Any:
    """The :class:`rough_map.export.costmap.CostmapSettings` of the costmap options."""
    from rough_map.export.costmap import CostmapSettings

    return CostmapSettings(
        lethal_speed=args.lethal_speed,
        lethal_classes=tuple(args.lethal_class or ()),
        mode=args.costmap_mode,
    )


def add_route_args(parser: argparse.ArgumentParser) -> None:
    """``--route FILE`` (the positional argument is then a height raster) and its options."""
    g = parser.add_argument_group(
        "a route over a height raster (the positional argument is then the raster: GeoTIFF, "
        "any GDAL raster, .crg, .las/.laz or .npy)"
    )
    g.add_argument(
        "--route",
        type=existing_path,
        metavar="FILE",
        help="GeoJSON LineString, or CSV of poses (x, y in m, optional yaw in rad and t in "
        "s), in the raster's CRS: each frame's patch is cut from the raster at its pose",
    )
    g.add_argument(
        "--every",
        type=positive_float("m"),
        default=0.448,
        metavar="M",
        help="distance between frames along a LineString (default 0.448 m, half the patch)",
    )
    g.add_argument(
        "--raster-spacing", type=positive_float("m"), metavar="M", help="cell size of a .npy"
    )
    g.add_argument(
        "--raster-origin",
        type=xy_metres,
        metavar="X,Y",
        help="north-west corner of a .npy raster in m (default 0,0)",
    )


def existing_path(text: str) -> Path:
    """Argument type: a file or folder that exists ("no such file or folder" otherwise)."""
    path = Path(text)
    try:
        path.stat()
    except FileNotFoundError:
        raise argparse.ArgumentTypeError(f"no such file or folder: {text!r:.200}") from None
    except (OSError, ValueError) as err:  # a name too long, a NUL byte, no permission
        why = err.strerror if isinstance(err, OSError) and err.strerror else str(err)
        raise argparse.ArgumentTypeError(f"cannot read {text!r:.200}: {why}") from None
    return path


# --------------------------------------------------------------------------- argument groups


def jobs(text: str) -> int:
    """Argument type of ``-j``: a number of processes >= 1, or -1 for every core."""
    value = _number(text, int)
    if value < 1 and value != -1:
        raise argparse.ArgumentTypeError(f"expected a number of processes >= 1 or -1, got {text!r}")
    return int(value)


#: ``--near-far`` choices -> ``rough_map.workflow.analyse``'s ``near_far``.
NEAR_FAR: dict[str, str | bool] = {"auto": "auto", "on": True, "off": False}


def add_map_args(parser: argparse.ArgumentParser, *, settings: bool = True) -> None:
    """``--resolution M`` and ``--near-far {auto,on,off}`` of the commands that map; with
    ``settings`` also the near-to-far settings (:func:`near_far_settings`)."""
    parser.add_argument(
        "--resolution",
        type=positive_float("m"),
        default=0.1,
        metavar="M",
        help="map cell size in m (default 0.1)",
    )
    parser.add_argument(
        "--near-far",
        choices=tuple(NEAR_FAR),
        default="auto",
        help="near-to-far from the stereo images (auto: when there are images)",
    )
    if not settings:
        return
    parser.add_argument(
        "--near-far-config",
        type=existing_path,
        default=None,
        metavar="FILE",
        help="near-to-far settings (YAML like configs/near_far.yaml; default the shipped one)",
    )
    shipped = _shipped_near_far()
    for flag, key, unit, help_text in (
        (
            "--far-tile",
            "tile_size_m",
            "m",
            "image tile side on the ground at the near-field patch, m",
        ),
        ("--far-range", "max_range_m", "m", "farthest far-field cell from the vehicle, m"),
        (
            "--far-weight",
            "weight",
            "1",
            "weight of a far-field prediction relative to a near-field patch",
        ),
        (
            "--far-confidence",
            "min_confidence",
            "1",
            "calibrated probability a far cell needs; below: unknown",
        ),
    ):
        text = (
            f"{help_text} (default: the config's {key}, {shipped.get(key, '?')} in the shipped one)"
        )
        parser.add_argument(flag, type=positive_float(unit), default=None, metavar="X", help=text)


def _shipped_near_far() -> dict[str, Any]:
    """The shipped ``configs/near_far.yaml`` as plain values, for the help ({} unreadable)."""
    import yaml

    from rough_map.resources import config_file

    try:
        with open(config_file("near_far.yaml"), encoding="utf-8") as f:
            values = yaml.safe_load(f)
    except (OSError, yaml.YAMLError):
        return {}
    return values if isinstance(values, dict) else {}


def near_far_settings(args: argparse.Namespace) -> Any:
    """The near-to-far settings of :func:`add_map_args`' options: the config file's (or the
    shipped one's), with the values given on the command line replacing its own."""
    from rough_map.near_far import load_near_far_settings

    settings = load_near_far_settings(args.near_far_config)
    update = {
        key: value
        for key, value in (
            ("tile_size_m", args.far_tile),
            ("max_range_m", args.far_range),
            ("weight", args.far_weight),
            ("min_confidence", args.far_confidence),
        )
        if value is not None
    }
    if update.get("min_confidence", 0.0) > 1.0:
        raise argparse.ArgumentTypeError("--far-confidence must be at most 1")
    return settings.model_copy(update=update)


def analysis_options(args: argparse.Namespace) -> dict[str, Any]:
    """The fields of :class:`rough_map.workflow.AnalysisOptions` that a mapping command's
    options give (:func:`add_map_args`, ``-j``, ``--roughness`` where it has one)."""
    return {
        "resolution": args.resolution,
        "near_far": NEAR_FAR[args.near_far],
        "near_far_settings": near_far_settings(args),
        "roughness": getattr(args, "roughness", "raw"),
        "n_jobs": args.jobs,
        "progress": args.progress,
        "vehicle": chosen_vehicle(args) if hasattr(args, "vehicle") else None,
        "speed": getattr(args, "speed", None),
    }


def add_jobs_arg(parser: argparse.ArgumentParser) -> None:
    """``-j/--jobs N``: worker processes for the frames (joblib)."""
    parser.add_argument(
        "-j",
        "--jobs",
        type=jobs,
        default=1,
        metavar="N",
        help="worker processes for the frames (default 1; -1: every core); the outputs are "
        "the same for any N",
    )


def add_cluster_args(parser: argparse.ArgumentParser) -> None:
    """``--scheduler ADDRESS`` and ``--tls CA CERT KEY``: a Dask cluster to run on
    (:func:`rough_map._cluster.cluster_client`)."""
    parser.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="Dask scheduler to run on, e.g. tcp://10.0.0.5:8786 or tls://... "
        "(keep it on a private network; see the README)",
    )
    parser.add_argument(
        "--tls",
        nargs=3,
        metavar=("CA", "CERT", "KEY"),
        help="PEM files for a tls:// scheduler: the CA, this client's certificate and key",
    )


def add_traverses_arg(
    parser: argparse.ArgumentParser, *, many: bool = False, tables: bool = True
) -> None:
    """The positional TRAVERSE (or TRAVERSE... with ``many``): folder, file or, with
    ``tables``, a features table (the commands that read the clouds take no table)."""
    text = ("labelled " if many else "") + "traverse folder or file (traverse.json or .yaml)"
    if tables:
        text += (
            ", or a features table (.csv or .parquet, with its metadata beside it) written "
            "by `rough-map features`"
        )
    parser.add_argument(
        "traverses" if many else "traverse",
        nargs="+" if many else None,
        type=existing_path if tables else traverse_path,
        metavar="TRAVERSE",
        help=text,
    )
    add_allow_outside_arg(parser)


def traverse_path(text: str) -> Path:
    """Argument type of the commands that read a traverse's clouds: an existing path that
    is not a features table."""
    path = existing_path(text)
    if path.suffix.lower() in (".csv", ".parquet"):
        raise argparse.ArgumentTypeError(
            f"{text!r:.120} is a features table; this command reads the traverse itself (its "
            "clouds give the elevation and the map): give its folder or traverse.json"
        )
    return path


def add_allow_outside_arg(parser: argparse.ArgumentParser) -> None:
    """``--allow-outside DIR`` (repeatable): folders outside a traverse folder whose files
    the traverse may name. Without it every path in a traverse (clouds, images,
    height_field), symbolic links followed, must resolve inside the traverse folder."""
    parser.add_argument(
        "--allow-outside",
        action="append",
        type=Path,
        default=None,
        metavar="DIR",
        help="also let the traverse name files under DIR, outside its folder (repeatable); "
        "by default every path in a traverse, symbolic links followed, must stay inside "
        "the traverse folder",
    )


def open_traverses(args: argparse.Namespace, sources: Any) -> list[Any]:
    """The TRAVERSE arguments ``sources`` (a path or a list of them) loaded as
    :class:`rough_map.io.traverse.Traverse` objects that allow the ``--allow-outside``
    folders; features tables (.csv, .parquet) stay paths.

    Raises
    ------
    FileFormatError, SchemaError
        A traverse file cannot be read or does not follow the schema.
    """
    from rough_map.io.traverse import load_traverse

    allowed = tuple(getattr(args, "allow_outside", None) or ())
    if getattr(args, "route", None) is not None:  # the source is a raster
        from rough_map.io.route import route_traverse

        return [
            route_traverse(
                Path(sources),
                args.route,
                every=args.every,
                spacing=args.raster_spacing,
                origin=args.raster_origin,
                allow_outside=allowed,
            )
        ]
    out: list[Any] = []
    for source in [sources] if isinstance(sources, str | Path) else sources:
        path = Path(source)
        if path.is_file() and path.suffix.lower() in (".csv", ".parquet"):
            out.append(path)
        else:
            out.append(load_traverse(path, allow_outside=allowed))
    return out


def add_model_arg(parser: argparse.ArgumentParser) -> None:
    """``--model M``: a model from ``rough-map train``, the same option in every command that
    classifies (default the shipped ``models/default``, :func:`chosen_model`)."""
    parser.add_argument(
        "--model",
        type=Path,
        default=None,
        metavar="M",
        help="model name or file (models/NAME or models/NAME.skops); default models/default "
        "shipped with rough_map",
    )


def chosen_model(args: argparse.Namespace) -> Path:
    """The model ``--model`` names, or the shipped default."""
    from rough_map.resources import model_base

    return Path(args.model) if args.model is not None else model_base()


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


def _spacing(text: str) -> float | str:
    """Argument type of ``--spacing``: ``auto`` or a grid step in m."""
    return "auto" if text.strip().lower() == "auto" else positive_float("m")(text)


def add_patch_args(parser: argparse.ArgumentParser, *, auto: bool = False) -> None:
    """--spacing/--size/--ahead/--lateral, all in metres; with ``auto``, ``--spacing auto``
    (the default there) coarsens the grid for sparse clouds."""
    g = parser.add_argument_group("patch of interest (vehicle frame, metres)")
    if auto:
        g.add_argument(
            "--spacing",
            type=_spacing,
            default="auto",
            metavar="M|auto",
            help=f"grid step B in m, or 'auto' (default): {DEFAULT_SPACING} m, or up to 4 "
            "times coarser when the cloud has too few points per cell for it; the band "
            "used is reported",
        )
    else:
        g.add_argument(
            "--spacing",
            type=positive_float("m"),
            default=DEFAULT_SPACING,
            metavar="M",
            help=f"grid step B in m (default {DEFAULT_SPACING})",
        )
    g.add_argument(
        "--size",
        type=positive_float("m"),
        default=DEFAULT_SIZE,
        metavar="M",
        help=f"side of the square patch in m (default {DEFAULT_SIZE})",
    )
    g.add_argument(
        "--ahead",
        type=finite_float("m"),
        default=DEFAULT_AHEAD,
        metavar="M",
        help=f"distance of the patch centre ahead of the vehicle in m (default {DEFAULT_AHEAD})",
    )
    g.add_argument(
        "--lateral",
        type=finite_float("m"),
        default=0.0,
        metavar="M",
        help="offset of the patch centre to the left in m (default 0.0)",
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
    """The patch of the ``--ahead/--size/--spacing/--lateral`` options (``--spacing auto``:
    the finest step, :data:`~rough_map.patch.DEFAULT_SPACING`).

    Raises
    ------
    InputError
        The options do not make a patch (fewer than 8 samples per profile).
    """
    spacing = DEFAULT_SPACING if args.spacing == "auto" else args.spacing
    return PatchSpec(ahead=args.ahead, size=args.size, spacing=spacing, lateral=args.lateral)


# --------------------------------------------------------------------------- output


def emit_json(obj: Any, *, indent: int | None = None) -> None:
    """One JSON document on stdout (NaN and inf become null).

    The whole document is built before anything is written, so an object JSON cannot hold
    raises without leaving half a document on stdout.
    """
    from rough_map.config import jsonable  # pydantic, yaml: only when JSON is printed

    text = json.dumps(jsonable(obj), indent=indent, separators=(",", ": "), allow_nan=False)
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


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
