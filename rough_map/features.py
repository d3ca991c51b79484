"""Features along a traverse: for every frame, the patch ahead and its PSD roughness.

For each frame of a :class:`~rough_map.io.traverse.Traverse` this

1. takes the frame's point cloud (vehicle frame), or reconstructs one from its stereo pair;
2. optionally compensates tilt with the frame's IMU roll and pitch (paper Eq. 11);
3. cuts and grids the patch of interest (:func:`rough_map.patch.grid_points`);
4. estimates R, w and their uncertainty along the direction of travel, and the same across
   it (anisotropy), with the gap policy of :mod:`rough_map.psd`;
5. records whether the patch is valid, and why not: too few points, too many empty cells,
   a patch the estimator refuses, no stereo pair to take the points from, an unreadable
   file. An invalid frame never stops the run.

The result is a :class:`FeatureTable`: one row per frame with the columns of
:data:`COLUMNS`, plus the patch-mean log10 PSD (``psd_01`` ... ) that the classifier uses.
"""

from __future__ import annotations

import csv
import json
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rough_map.errors import FileFormatError, InputError, RoughMapError
from rough_map.patch import Extraction, PatchSpec, grid_points
from rough_map.psd import patch_roughness

log = logging.getLogger(__name__)

#: Columns of a features table, in order (spectrum columns follow).
COLUMNS = (
    "frame",
    "t",
    "x",
    "y",
    "yaw",
    "R",
    "w",
    "sigma_R",
    "sigma_w",
    "rms",
    "iso_class",
    "n_points",
    "valid",
    "reason",
    "label",
    "R_lat",
    "w_lat",
    "fit_residual",
    "fill",
    "point_noise",
    "noise_psd",
    "level_angle",
)
_TEXT = {"iso_class", "reason", "label"}
_BOOL = {"valid"}
_INT = {"frame", "n_points"}


@dataclass
class FeatureTable:
    """Per-frame features of a traverse.

    Attributes
    ----------
    columns : dict of str to ndarray
        The :data:`COLUMNS` (R in m^3/rad, rms in m, t in s, x/y in m, yaw in rad, ...).
    omega : ndarray
        Wavenumbers in rad/m of the spectrum columns.
    log_psd : ndarray, shape (n_frames, len(omega))
        log10 of the patch-mean PSD in m^3/rad (NaN rows for invalid frames).
    name : str
        Name of the traverse.
    """

    columns: dict[str, np.ndarray]
    omega: np.ndarray
    log_psd: np.ndarray
    name: str = ""
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.columns["t"])

    def __getitem__(self, key: str) -> np.ndarray:
        return self.columns[key]

    @property
    def valid(self) -> np.ndarray:
        return self.columns["valid"].astype(bool)

    def distance(self) -> np.ndarray:
        """Cumulative distance travelled along the path, m (from the poses)."""
        x, y = self.columns["x"], self.columns["y"]
        step = np.hypot(np.diff(x), np.diff(y))
        return np.concatenate([[0.0], np.cumsum(step)])

    def spectrum_names(self) -> list[str]:
        return [f"psd_{k:02d}" for k in range(1, self.omega.size + 1)]


def frame_features(
    points: np.ndarray,
    spec: PatchSpec,
    *,
    roll: float | None = None,
    pitch: float | None = None,
    method: str = "unbiased",
    subtract_noise: bool = True,
    min_points: int = 2000,
    min_fill: float = 0.7,
) -> tuple[dict, np.ndarray | None, np.ndarray | None]:
    """Features of one frame's cloud; never raises for a bad patch (valid=False instead).

    Returns (row, omega, mean PSD in m^3/rad) where row holds the scalar columns.
    """
    row: dict = {"valid": False, "reason": "", "n_points": 0}
    try:
        grid = grid_points(points, spec, roll=roll, pitch=pitch, min_points=min_points)
    except RoughMapError as exc:
        row["reason"] = f"too few points: {exc}" if "points" in str(exc) else str(exc)
        return row, None, None
    row.update(
        n_points=grid.n_points,
        fill=grid.fill_fraction,
        point_noise=grid.point_noise,
        noise_psd=grid.noise_psd,
        level_angle=grid.level_angle,
    )
    if grid.fill_fraction < min_fill:
        row["reason"] = f"too many gaps: {grid.fill_fraction:.0%} of cells filled"
        return row, None, None
    noise = grid.noise_psd if subtract_noise and math.isfinite(grid.noise_psd) else None
    try:
        lon = patch_roughness(
            grid.heights,
            spec.spacing,
            method=method,
            noise_psd=noise,
            subtract_noise=noise is not None,
            gridding=grid.gridding,
        )
        lat = patch_roughness(
            grid.heights.T,
            spec.spacing,
            method=method,
            noise_psd=noise,
            subtract_noise=noise is not None,
            gridding=grid.gridding,
        )
    except RoughMapError as exc:
        row["reason"] = str(exc)
        return row, None, None
    row.update(
        valid=True,
        R=lon.R,
        w=lon.w,
        sigma_R=lon.sigma_R,
        sigma_w=lon.sigma_w,
        rms=lon.rms,
        iso_class=lon.iso_class,
        R_lat=lat.R,
        w_lat=lat.w,
        fit_residual=lon.fit_residual,
    )
    return row, lon.omega, lon.psd


def traverse_features(
    traverse,
    spec: PatchSpec | None = None,
    *,
    use_imu: bool = True,
    source: str = "auto",
    method: str = "unbiased",
    subtract_noise: bool = True,
    min_points: int = 2000,
    min_fill: float = 0.7,
    progress: bool = False,
) -> FeatureTable:
    """Features of every frame of a traverse.

    Parameters
    ----------
    traverse : Traverse or path
        A loaded traverse, or its folder / file.
    spec : PatchSpec, optional
        Patch geometry (default: 0.896 m square, 1 m ahead, 8 mm).
    use_imu : bool
        Compensate tilt with the frames' IMU roll/pitch when they have one.
    source : {"auto", "cloud", "stereo"}
        Where the points come from: the frame's cloud, its stereo pair, or the cloud when
        there is one ("auto").
    method : {"unbiased", "paper"}
        Estimator (see :func:`rough_map.psd.patch_roughness`).
    subtract_noise : bool
        Subtract the noise floor estimated from the within-cell scatter.
    min_points : int
        Fewest points in the patch for a valid frame.
    min_fill : float
        Smallest fraction of filled cells for a valid frame.
    progress : bool
        Progress bar on stderr.
    """
    from tqdm import tqdm

    from rough_map.io.traverse import Traverse, load_traverse

    if not isinstance(traverse, Traverse):
        traverse = load_traverse(traverse)
    if source not in ("auto", "cloud", "stereo"):
        raise InputError(f"source must be 'auto', 'cloud' or 'stereo', got {source!r}")
    if source == "stereo" and traverse.spec.calibration is None:
        raise InputError(f"{traverse.name}: stereo needs a 'calibration' in the traverse")
    spec = spec or PatchSpec()
    stereo = _StereoSource(traverse, spec)  # reads nothing until a frame needs it
    n = len(traverse)
    rows: list[dict] = []
    spectra: list[np.ndarray | None] = []
    omega = None
    for i in tqdm(range(n), desc=f"features {traverse.name}", unit="frame", disable=not progress):
        frame = traverse.frames[i]
        row, om, psd = _frame_row(
            traverse,
            i,
            spec,
            source,
            stereo,
            use_imu=use_imu,
            method=method,
            subtract_noise=subtract_noise,
            min_points=min_points,
            min_fill=min_fill,
        )
        if om is not None:
            omega = om
        if not row["valid"]:
            log.info("frame %d invalid: %s", i, row["reason"])
        row.update(
            frame=i,
            t=frame.t,
            x=frame.pose.x,
            y=frame.pose.y,
            yaw=frame.pose.yaw,
            label=frame.label or "",
        )
        rows.append(row)
        spectra.append(psd)
    if omega is None:
        omega = 2 * np.pi * np.arange(1, spec.n // 2 + 1) / (spec.n * spec.spacing)
    log_psd = np.full((n, omega.size), np.nan)
    for i, s in enumerate(spectra):
        if s is not None:
            log_psd[i] = np.log10(s)
    n_invalid = sum(not r["valid"] for r in rows)
    if n_invalid:
        log.warning("%s: %d of %d frames have no valid patch", traverse.name, n_invalid, n)
    return FeatureTable(_columns(rows), omega, log_psd, traverse.name)


def _columns(rows: list[dict]) -> dict[str, np.ndarray]:
    cols = {}
    for c in COLUMNS:
        if c in _TEXT:
            cols[c] = np.array([str(r.get(c, "") or "") for r in rows], dtype=object)
        elif c in _BOOL:
            cols[c] = np.array([bool(r.get(c, False)) for r in rows])
        elif c in _INT:
            cols[c] = np.array([int(r.get(c, 0)) for r in rows])
        else:
            cols[c] = np.array([float(r.get(c, math.nan)) for r in rows])
    return cols


def _frame_row(
    traverse,
    i: int,
    spec: PatchSpec,
    source: str,
    stereo: _StereoSource,
    *,
    use_imu: bool,
    **options,
) -> tuple[dict, np.ndarray | None, np.ndarray | None]:
    """:func:`frame_features` of frame ``i``, or an invalid row saying why there are no
    points: no stereo pair, an unreadable file."""
    frame = traverse.frames[i]
    use_stereo = source == "stereo" or (source == "auto" and frame.cloud is None)
    if use_stereo and (frame.left is None or frame.right is None):
        # Stereo is often recorded at a lower rate than the clouds: not an error of the run.
        return {"valid": False, "reason": "no stereo pair", "n_points": 0}, None, None
    try:
        points = stereo.cloud(i) if use_stereo else traverse.load_cloud(i)
    except FileFormatError as exc:
        return {"valid": False, "reason": f"unreadable: {exc}", "n_points": 0}, None, None
    roll = pitch = None
    if use_imu and frame.imu is not None:
        roll, pitch = frame.imu.roll, frame.imu.pitch
    return frame_features(points, spec, roll=roll, pitch=pitch, **options)


class _StereoSource:
    """Clouds from a traverse's stereo pairs (lazy, so clouds-only runs need no OpenCV)."""

    def __init__(self, traverse, spec: PatchSpec) -> None:
        self.traverse = traverse
        self.spec = spec

    @property
    def calib(self):
        if self.traverse.spec.calibration is None:
            raise InputError(f"{self.traverse.name}: stereo needs a 'calibration' in the traverse")
        return self.traverse.spec.calibration

    def cloud(self, i: int) -> np.ndarray:
        """The cloud of frame ``i``'s stereo pair (vehicle frame, m), over the patch."""
        from rough_map.stereo import read_image, stereo_to_cloud

        frame = self.traverse.frames[i]
        left = read_image(self.traverse.resolve(frame.left))
        right = read_image(self.traverse.resolve(frame.right))
        return stereo_to_cloud(
            left,
            right,
            self.calib,
            ahead=self.spec.ahead,
            size=self.spec.n * self.spec.spacing,
            lateral=self.spec.lateral,
        )


# --------------------------------------------------------------------------- files

#: ``format`` of the metadata of a features table.
FEATURES_FORMAT = "rough_map features"
#: Version of that metadata; a reader refuses a newer one.
FEATURES_FORMAT_VERSION = 1

#: Units of the columns of a features table ("" for counts, flags, text and ratios).
COLUMN_UNITS = {
    "frame": "",
    "t": "s",
    "x": "m",
    "y": "m",
    "yaw": "rad",
    "R": "m³/rad",
    "w": "",
    "sigma_R": "m³/rad",
    "sigma_w": "",
    "rms": "m",
    "iso_class": "",
    "n_points": "",
    "valid": "",
    "reason": "",
    "label": "",
    "R_lat": "m³/rad",
    "w_lat": "",
    "fit_residual": "",
    "fill": "",
    "point_noise": "m",
    "noise_psd": "m³/rad",
    "level_angle": "rad",
}


def features_metadata_path(path: str | Path) -> Path:
    """Where the metadata of a features CSV lives: ``features.csv`` -> ``features.csv.json``."""
    path = Path(path)
    return path.with_name(path.name + ".json")


def features_metadata(table: FeatureTable) -> dict:
    """The metadata of a features table: format, traverse name, the wavenumbers (rad/m) of
    the ``psd_NN`` columns, and the units of every column.

    A CSV keeps it in a JSON file beside it (:func:`features_metadata_path`), so that the CSV
    itself is plain (first line the header); a Parquet file in its key-value metadata under
    ``rough_map``.
    """
    from rough_map import __version__

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


def write_features(table: FeatureTable, path: str | Path) -> Path:
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
    from rough_map._files import atomic_output

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
        arrays = {k: (list(v) if k in _TEXT else v) for k, v in data.items()}
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


def _fmt(v) -> str:
    if isinstance(v, bool | np.bool_):
        return "true" if v else "false"
    if isinstance(v, float | np.floating):
        return "" if not math.isfinite(v) else f"{float(v):.9g}"
    return str(v)


def read_features(path: str | Path) -> FeatureTable:
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
    missing = [c for c in COLUMNS if c not in raw]
    if missing:
        raise FileFormatError(path, f"missing columns {missing}", field=missing[0])
    cols: dict[str, np.ndarray] = {}
    for c in COLUMNS:
        v = raw[c]
        try:
            if c in _TEXT:
                cols[c] = np.array(["" if x is None else str(x) for x in v], dtype=object)
            elif c in _BOOL:
                cols[c] = np.array([str(x).lower() in ("true", "1") for x in v])
            elif c in _INT:
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


def _read_parquet(path: Path) -> tuple[dict[str, np.ndarray], dict]:
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


def _read_csv(path: Path) -> tuple[dict[str, np.ndarray], dict]:
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


def _csv_metadata(path: Path, header: list[str]) -> dict:
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


def _parse_metadata(text: str, where: Path, what: str) -> dict:
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


def feature_tables(
    sources: Sequence[str | Path],
    extraction: dict[str, Any] | None = None,
    *,
    progress: bool = False,
) -> list[Any]:
    """Feature tables of traverses, computing them or reading them from files.

    Parameters
    ----------
    sources : sequence of str or Path
        Traverse folders or files (features are computed with ``extraction``), or features
        tables (``.csv``/``.parquet`` written by ``rough-map features``, read as they are).
    extraction : Extraction or dict, optional
        The patch and estimator options (:class:`rough_map.patch.Extraction`, or its
        ``to_dict`` form as a model records it); default the paper's.
    progress : bool
        Progress bars on stderr.

    Returns
    -------
    list of FeatureTable
    """
    ex = Extraction.from_dict(extraction)
    tables = []
    for source in sources:
        path = Path(source)
        if path.is_file() and path.suffix.lower() in (".csv", ".parquet"):
            tables.append(read_features(path))
        else:
            tables.append(
                traverse_features(
                    path,
                    ex.patch,
                    use_imu=ex.use_imu,
                    method=ex.method,
                    subtract_noise=ex.subtract_noise,
                    progress=progress,
                )
            )
    return tables
