"""Features tables on disk: plain CSV with a JSON metadata file beside it, or Parquet.

The CSV's first line is its header (``csv.DictReader`` and ``pandas.read_csv`` read it with
no options); the metadata (:func:`features_metadata`: format, traverse name, the
wavenumbers of the ``psd_NN`` columns and the units of every column) is in
``<file>.json`` (:func:`features_metadata_path`). A Parquet file keeps the same metadata
in its key-value metadata under ``rough_map``.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from rough_map import __version__
from rough_map._files import PathLike, atomic_output
from rough_map.errors import FileFormatError, InputError
from rough_map.features.table import (
    BOOL_COLUMNS,
    COLUMN_UNITS,
    COLUMNS,
    INT_COLUMNS,
    OPTIONAL_COLUMNS,
    TEXT_COLUMNS,
    FeatureTable,
)

__all__ = [
    "FEATURES_FORMAT",
    "FEATURES_FORMAT_VERSION",
    "features_metadata",
    "features_metadata_path",
    "read_features",
    "write_features",
]

#: ``format`` of the metadata of a features table.
FEATURES_FORMAT = "rough_map features"
#: Version of that metadata; a reader refuses a newer one.
FEATURES_FORMAT_VERSION = 1


def features_metadata_path(path: PathLike) -> Path:
    """Where the metadata of a features CSV lives: ``features.csv`` -> ``features.csv.json``."""
    path = Path(path)
    return path.with_name(path.name + ".json")


def features_metadata(table: FeatureTable) -> dict[str, Any]:
    """The metadata of a features table: format, traverse name, the wavenumbers (rad/m) of
    the ``psd_NN`` columns, and the units of every column.

    A CSV keeps it in a JSON file beside it (:func:`features_metadata_path`), so that the CSV
    itself is plain (first line the header); a Parquet file in its key-value metadata under
    ``rough_map``.
    """
    names = table.spectrum_names()
    return {
        "format": FEATURES_FORMAT,
        "format_version": FEATURES_FORMAT_VERSION,
        "name": table.name,
        "rough_map_version": __version__,
        "frames": len(table),
        "omega_rad_per_m": [float(o) for o in table.omega],
        "spectrum_columns": names,
        "units": {**COLUMN_UNITS, **dict.fromkeys(names, "log10(m³/rad)")},
    }


def write_features(table: FeatureTable, path: PathLike) -> Path:
    """Write a features table as .csv (plus ``<path>.json``), or .parquet (needs pyarrow).

    The CSV is plain: its first line is the header, so ``csv.DictReader`` and
    ``pandas.read_csv`` read it with no options. Its metadata (:func:`features_metadata`:
    the traverse name and the wavenumbers of the ``psd_NN`` columns, which
    :func:`read_features` needs) is written to ``<path>.json`` beside it, e.g.
    ``features.csv.json``. Parquet keeps the same metadata in its key-value metadata.
    Both files are written atomically, the metadata first.

    Returns
    -------
    Path
        ``path`` (the table; the metadata is at :func:`features_metadata_path`).
    """
    path = Path(path)
    names = list(COLUMNS) + table.spectrum_names()
    data = dict(table.columns)
    for k, name in enumerate(table.spectrum_names()):
        data[name] = table.log_psd[:, k]
    meta_text = json.dumps(features_metadata(table), indent=1, ensure_ascii=False)
    suffix = path.suffix.lower()
    if suffix == ".parquet":
        try:
            import pyarrow as pa
            import pyarrow.parquet as pq
        except ImportError:
            raise InputError("writing .parquet needs pyarrow: pip install pyarrow") from None
        arrays = {k: (list(v) if k in TEXT_COLUMNS else v) for k, v in data.items()}
        tbl = pa.table(arrays).replace_schema_metadata({b"rough_map": meta_text.encode()})
        with atomic_output(path) as tmp:
            pq.write_table(tbl, tmp)
        return path
    if suffix != ".csv":
        raise InputError(f"features are written as .csv or .parquet, not {path.suffix!r}")
    with atomic_output(features_metadata_path(path)) as tmp:
        tmp.write_text(meta_text + "\n", encoding="utf-8")
    with atomic_output(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(names)
        for i in range(len(table)):
            writer.writerow([_fmt(data[c][i]) for c in names])
    return path


def _fmt(v: object) -> str:
    if isinstance(v, bool | np.bool_):
        return "true" if v else "false"
    if isinstance(v, float | np.floating):
        return "" if not math.isfinite(v) else f"{float(v):.9g}"
    return str(v)


def read_features(path: PathLike) -> FeatureTable:
    """Read a table written by :func:`write_features` (.csv with its .json, or .parquet).

    Tables written by rough_map 0.1, whose CSV began with a ``# rough_map features`` line
    holding the wavenumbers, are read too.

    Raises
    ------
    FileFormatError
        No such file; a CSV whose metadata file is missing or damaged; a missing column or a
        bad value (naming the column).
    """
    path = Path(path)
    if not path.is_file():
        raise FileFormatError(path, "no such features file")
    if path.suffix.lower() == ".parquet":
        raw, meta = _read_parquet(path)
    else:
        raw, meta = _read_csv(path)
    omega = np.asarray(meta["omega"], dtype=float)
    name = meta["name"]
    missing = [c for c in COLUMNS if c not in raw and c not in OPTIONAL_COLUMNS]
    if missing:
        raise FileFormatError(path, f"missing columns {missing}", field=missing[0])
    n_rows = len(next(iter(raw.values()))) if raw else 0
    cols: dict[str, np.ndarray] = {}
    for c in COLUMNS:
        v = raw[c] if c in raw else np.full(n_rows, "", dtype=object)  # an older table
        try:
            if c in TEXT_COLUMNS:
                cols[c] = np.array(["" if x is None else str(x) for x in v], dtype=object)
            elif c in BOOL_COLUMNS:
                cols[c] = np.array([str(x).lower() in ("true", "1") for x in v])
            elif c in INT_COLUMNS:
                cols[c] = np.array([int(float(x)) if str(x) != "" else 0 for x in v])
            else:
                cols[c] = np.array([float(x) if x not in ("", None) else math.nan for x in v])
        except ValueError as exc:
            raise FileFormatError(path, f"bad value: {exc}", field=c) from None
    names = [f"psd_{k:02d}" for k in range(1, omega.size + 1)]
    try:
        log_psd = (
            np.column_stack(
                [
                    np.array([float(x) if x not in ("", None) else math.nan for x in raw[n]])
                    for n in names
                ]
            )
            if names
            else np.zeros((len(cols["t"]), 0))
        )
    except KeyError as exc:
        raise FileFormatError(path, "missing spectrum column", field=str(exc)) from None
    except ValueError as exc:
        raise FileFormatError(path, f"bad value in a spectrum column: {exc}") from None
    return FeatureTable(cols, omega, log_psd, name)


def _read_parquet(path: Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    try:
        import pyarrow.parquet as pq
    except ImportError:
        raise InputError("reading .parquet needs pyarrow: pip install pyarrow") from None
    tbl = pq.read_table(path)
    kv = tbl.schema.metadata or {}
    raw = {k: np.asarray(tbl[k].to_pylist(), dtype=object) for k in tbl.column_names}
    if b"rough_map" in kv:
        meta = _parse_metadata(kv[b"rough_map"].decode(), path, "Parquet metadata 'rough_map'")
    elif b"omega" in kv:  # rough_map 0.1
        omega = [float(v) for v in kv[b"omega"].decode().split(",") if v]
        meta = {"omega": omega, "name": kv.get(b"name", b"").decode()}
    else:
        raise FileFormatError(path, "no rough_map metadata: not written by rough-map features")
    return raw, meta


def _read_csv(path: Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    with open(path, newline="", encoding="utf-8") as fh:
        first = fh.readline()
        if first.startswith("# rough_map features"):  # rough_map 0.1: metadata in line 1
            if "omega_rad_per_m=" not in first:
                raise FileFormatError(path, "not a rough_map features table (header line)")
            meta = {
                "name": first[len("# rough_map features of ") :].split(";")[0],
                "omega": [float(v) for v in first.split("omega_rad_per_m=")[1].split(",")],
            }
        else:
            fh.seek(0)
            meta = None
        reader = csv.reader(fh)
        header = next(reader, None)
        if header is None:
            raise FileFormatError(path, "empty: no column header")
        body = list(reader)
    if meta is None:
        meta = _csv_metadata(path, header)
    raw = {
        h: np.array([r[j] if j < len(r) else "" for r in body], dtype=object)
        for j, h in enumerate(header)
    }
    return raw, meta


def _csv_metadata(path: Path, header: list[str]) -> dict[str, Any]:
    sidecar = features_metadata_path(path)
    if not sidecar.is_file():
        if not any(h.startswith("psd_") for h in header):
            return {"name": path.stem, "omega": []}  # nothing that needs the metadata
        raise FileFormatError(
            path,
            f"its metadata file {sidecar.name} is missing (it holds the wavenumbers of the "
            "psd_NN columns); keep the two files together, or write the table again with "
            "`rough-map features`",
        )
    try:
        text = sidecar.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise FileFormatError(sidecar, f"cannot read the metadata: {exc}") from None
    meta = _parse_metadata(text, sidecar, "metadata")
    n_psd = sum(h.startswith("psd_") for h in header)
    if len(meta["omega"]) != n_psd:
        raise FileFormatError(
            sidecar,
            f"{len(meta['omega'])} wavenumbers for {n_psd} psd_NN columns in {path.name}",
            field="omega_rad_per_m",
        )
    return meta


def _parse_metadata(text: str, where: Path, what: str) -> dict[str, Any]:
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise FileFormatError(where, f"{what} is not JSON: {exc}") from None
    if not isinstance(doc, dict) or doc.get("format") != FEATURES_FORMAT:
        raise FileFormatError(where, f"{what} is not rough_map features metadata", "format")
    version = doc.get("format_version")
    if not isinstance(version, int) or version > FEATURES_FORMAT_VERSION:
        raise FileFormatError(
            where,
            f"format_version {version!r}; this rough_map reads up to {FEATURES_FORMAT_VERSION}",
            "format_version",
        )
    omega = doc.get("omega_rad_per_m")
    if not (
        isinstance(omega, list)
        and all(isinstance(o, int | float) and not isinstance(o, bool) for o in omega)
    ):
        raise FileFormatError(where, "must be a list of numbers (rad/m)", "omega_rad_per_m")
    return {"name": str(doc.get("name", "")), "omega": [float(o) for o in omega]}
