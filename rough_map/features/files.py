"""Features tables on disk: plain CSV with a JSON metadata file beside it, or Parquet.

The CSV's first line is its header (``csv.DictReader`` and ``pandas.read_csv`` read it with
no options); the metadata (:func:`features_metadata`: format, traverse name, the
wavenumbers of the ``psd_NN`` columns and the units of every column) is in
``<file>.json`` (:func:`features_metadata_path`). A Parquet file keeps the same metadata
in its key-value metadata under ``rough_map``.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from rough_map import __version__
from rough_map._bounded import clip, parse_json, read_document_text, short
from rough_map._files import PathLike, atomic_output, atomic_outputs, resolve_pending
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
    the ``psd_NN`` columns, the units of every column, and ``row_spacing_m``, the width in
    m of pooled rows, when the table has them (:attr:`FeatureTable.row_spacing`).

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
        **({} if table.row_spacing is None else {"row_spacing_m": table.row_spacing}),
    }


def write_features(table: FeatureTable, path: PathLike) -> Path:
    """Write a features table as .csv (plus ``<path>.json``), or .parquet (needs pyarrow).

    The CSV is plain: its first line is the header, so ``csv.DictReader`` and
    ``pandas.read_csv`` read it with no options. Its metadata (:func:`features_metadata`:
    the traverse name and the wavenumbers of the ``psd_NN`` columns, which
    :func:`read_features` needs) is written to ``<path>.json`` beside it, e.g.
    ``features.csv.json``. Parquet keeps the same metadata in its key-value metadata.
    The two files are one set (:func:`rough_map._files.atomic_outputs`): they replace old
    ones together, and a run killed between the renames is finished by the next read or
    write. The metadata holds the table's SHA-256 (``table_sha256``), so a table edited
    since shows.

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
    buf = io.StringIO(newline="")
    writer = csv.writer(buf)
    writer.writerow(names)
    for start in range(0, len(table), _ROWS_AT_ONCE):
        rows = slice(start, start + _ROWS_AT_ONCE)
        writer.writerows(zip(*(_column_text(data[c][rows]) for c in names), strict=True))
    body = buf.getvalue().encode("utf-8")
    meta = features_metadata(table)
    meta["table_sha256"] = hashlib.sha256(body).hexdigest()  # ties the pair together
    meta_text = json.dumps(meta, indent=1, ensure_ascii=False)
    # one set: both files are written, checked and flushed before either takes its name,
    # and a run killed between the two renames is finished by the next read or write
    # (rough_map._files.atomic_outputs); table_sha256 still shows a table edited since
    with atomic_outputs([path, features_metadata_path(path)]) as (table_tmp, meta_tmp):
        table_tmp.write_bytes(body)
        meta_tmp.write_text(meta_text + "\n", encoding="utf-8")
    return path


def _check_pair(path: Path, sidecar: Path, text: str) -> None:
    """Warn when a CSV is not the one its metadata was written with (``table_sha256``):
    edited since, or a run killed between the renames of the pair."""
    try:
        expected = json.loads(text).get("table_sha256")
        if not isinstance(expected, str):
            return  # written before rough_map recorded it
        actual = hashlib.sha256(path.read_bytes()).hexdigest()
    except (OSError, ValueError, AttributeError):
        return
    if actual != expected:
        logging.getLogger(__name__).warning(
            "%s is not the table its metadata %s was written with (edited since, or an "
            "interrupted write): check it, or write it again with rough-map features",
            path,
            sidecar.name,
        )


#: Rows of a CSV formatted at once (a column at a time).
_ROWS_AT_ONCE = 1024


def _column_text(values: Any) -> list[str]:
    """The CSV text of a column's values (:func:`_fmt` of each), a whole column at once."""
    if isinstance(values, np.ndarray) and values.ndim == 1:
        kind = values.dtype.kind
        if kind == "b":
            return ["true" if v else "false" for v in values.tolist()]
        if kind == "f":
            return ["" if not math.isfinite(v) else f"{v:.9g}" for v in values.tolist()]
        if kind in "iu":
            return [str(v) for v in values.tolist()]
    return [_fmt(v) for v in values]


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
    try:
        there = path.is_file()
    except OSError:  # a name too long
        there = False
    else:  # a write of the table and its metadata killed between the renames: finish it
        resolve_pending([path, features_metadata_path(path)])
        there = path.is_file()
    if not there:
        raise FileFormatError(path, "no such features file")
    if path.suffix.lower() == ".parquet":
        raw, meta = _read_parquet(path)
    else:
        raw, meta = _read_csv(path)
    omega = np.asarray(meta["omega"], dtype=float)
    if omega.size and not (np.all(np.isfinite(omega)) and np.all(omega > 0)):
        raise FileFormatError(path, "wavenumbers must be finite and positive", "omega_rad_per_m")
    name = meta["name"]
    missing = [c for c in COLUMNS if c not in raw and c not in OPTIONAL_COLUMNS]
    if missing:
        raise FileFormatError(path, f"missing columns {clip(str(missing), 80)}", field=missing[0])
    n_rows = len(next(iter(raw.values()))) if raw else 0
    cols: dict[str, np.ndarray] = {}
    for c in COLUMNS:
        v = raw[c] if c in raw else np.full(n_rows, "", dtype=object)  # an older table
        if c in TEXT_COLUMNS:
            cols[c] = np.array(["" if x is None else str(x) for x in v], dtype=object)
        elif c in BOOL_COLUMNS:
            cols[c] = np.array([str(x).lower() in ("true", "1") for x in v], dtype=bool)
        else:
            cols[c] = _numbers(path, c, v, integer=c in INT_COLUMNS)
    names = [f"psd_{k:02d}" for k in range(1, omega.size + 1)]
    absent = [n for n in names if n not in raw]
    if absent:
        raise FileFormatError(path, "missing spectrum column", field=absent[0])
    log_psd = (
        np.column_stack([_numbers(path, n, raw[n]) for n in names])
        if names
        else np.zeros((n_rows, 0))
    )
    return FeatureTable(cols, omega, log_psd, name, meta.get("row_spacing"))


def _numbers(path: Path, column: str, values: Any, integer: bool = False) -> np.ndarray:
    """A numeric column (empty cells: NaN, or 0 for integers), or a FileFormatError naming
    the column and the row of the first bad cell."""
    out = np.empty(len(values), dtype=np.int64 if integer else float)
    for i, x in enumerate(values):
        try:
            if x in ("", None):
                out[i] = 0 if integer else math.nan
            elif integer:
                out[i] = int(float(x))  # "3.0" too
            else:
                out[i] = float(x)
        except (ValueError, TypeError, OverflowError):
            kind = "a whole number" if integer else "a number"
            raise FileFormatError(
                path, f"row {i + 1}: expected {kind}, got {short(x, 40)}", field=column
            ) from None
    return out


def _read_parquet(path: Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    try:
        import pyarrow.parquet as pq
    except ImportError:
        raise InputError("reading .parquet needs pyarrow: pip install pyarrow") from None
    import pyarrow as pa

    try:
        tbl = pq.read_table(path)
        kv = tbl.schema.metadata or {}
        raw = {k: np.asarray(tbl[k].to_pylist(), dtype=object) for k in tbl.column_names}
    except (pa.ArrowException, OSError, ValueError, TypeError, MemoryError) as exc:
        raise FileFormatError(path, f"not a readable Parquet file: {clip(str(exc), 80)}") from None
    if b"rough_map" in kv:
        text = kv[b"rough_map"].decode("utf-8", "replace")
        meta = _parse_metadata(text, path, "Parquet metadata 'rough_map'")
    elif b"omega" in kv:  # rough_map 0.1
        text = kv[b"omega"].decode("utf-8", "replace")
        meta = {
            "omega": _old_omega(text, path),
            "name": kv.get(b"name", b"").decode("utf-8", "replace"),
        }
    else:
        raise FileFormatError(path, "no rough_map metadata: not written by rough-map features")
    return raw, meta


def _read_csv(path: Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    try:
        text = path.read_bytes().decode("utf-8")
    except OSError as exc:
        raise FileFormatError(path, f"cannot read: {clip(str(exc.strerror or exc), 60)}") from None
    except UnicodeDecodeError as exc:
        raise FileFormatError(path, f"not UTF-8 text (byte {exc.start})") from None
    fh = io.StringIO(text, newline="")
    first = fh.readline()
    meta: dict[str, Any] | None = None
    if first.startswith("# rough_map features"):  # rough_map 0.1: metadata in line 1
        if "omega_rad_per_m=" not in first:
            raise FileFormatError(path, "not a rough_map features table (header line)")
        meta = {
            "name": first[len("# rough_map features of ") :].split(";")[0].strip(),
            "omega": _old_omega(first.split("omega_rad_per_m=")[1], path),
        }
    else:
        fh.seek(0)
    try:
        reader = csv.reader(fh)
        header = next(reader, None)
        if header is None:
            raise FileFormatError(path, "empty: no column header")
        body = list(reader)
    except csv.Error as exc:
        raise FileFormatError(path, f"not a CSV table: {clip(str(exc), 60)}") from None
    duplicated = sorted({h for h in header if header.count(h) > 1})
    if duplicated:
        raise FileFormatError(path, "a column appears twice", field=clip(duplicated[0], 40))
    if meta is None:
        meta = _csv_metadata(path, header)
    raw = {
        h: np.array([r[j] if j < len(r) else "" for r in body], dtype=object)
        for j, h in enumerate(header)
    }
    return raw, meta


def _old_omega(text: str, path: Path) -> list[float]:
    """The wavenumbers of a rough_map 0.1 table (comma-separated, rad/m)."""
    try:
        return [float(v) for v in text.strip().split(",") if v.strip()]
    except ValueError:
        raise FileFormatError(
            path, f"expected numbers, got {short(text.strip(), 40)}", "omega_rad_per_m"
        ) from None


def _csv_metadata(path: Path, header: list[str]) -> dict[str, Any]:
    sidecar = features_metadata_path(path)
    if not sidecar.is_file():
        if not any(h.startswith("psd_") for h in header):
            return {"name": path.stem, "omega": []}  # nothing that needs the metadata
        raise FileFormatError(
            path,
            f"its metadata file {sidecar.name} is missing (it holds the wavenumbers of the "
            "psd_NN columns); keep them together or rerun `rough-map features`",
        )
    text = read_document_text(sidecar)
    meta = _parse_metadata(text, sidecar, "metadata")
    _check_pair(path, sidecar, text)
    n_psd = sum(h.startswith("psd_") for h in header)
    if len(meta["omega"]) != n_psd:
        raise FileFormatError(
            sidecar,
            f"{len(meta['omega'])} wavenumbers for {n_psd} psd_NN columns in {path.name}",
            field="omega_rad_per_m",
        )
    return meta


def _parse_metadata(text: str, where: Path, what: str) -> dict[str, Any]:
    doc = parse_json(text, where)
    if not isinstance(doc, dict) or doc.get("format") != FEATURES_FORMAT:
        raise FileFormatError(where, f"{what} is not rough_map features metadata", "format")
    version = doc.get("format_version")
    if not isinstance(version, int) or version > FEATURES_FORMAT_VERSION:
        raise FileFormatError(
            where,
            f"format_version {short(version, 30)}; this rough_map reads up to "
            f"{FEATURES_FORMAT_VERSION}",
            "format_version",
        )
    omega = doc.get("omega_rad_per_m")
    if not (
        isinstance(omega, list)
        and all(isinstance(o, int | float) and not isinstance(o, bool) for o in omega)
    ):
        raise FileFormatError(where, "must be a list of numbers (rad/m)", "omega_rad_per_m")
    width = doc.get("row_spacing_m")
    if width is not None and not (
        isinstance(width, int | float)
        and not isinstance(width, bool)
        and math.isfinite(width)
        and width > 0
    ):
        raise FileFormatError(where, "must be a positive width in m", "row_spacing_m")
    return {
        "name": str(doc.get("name", "")),
        "omega": [float(o) for o in omega],
        "row_spacing": None if width is None else float(width),
    }
