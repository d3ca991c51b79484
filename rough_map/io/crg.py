"""ASAM OpenCRG road surfaces (``.crg``): a regular grid of heights along a reference line.

A CRG file is text sections (``$CT`` comments, ``$ROAD_CRG`` parameters, ``$KD_Definition``
channels, options and modifiers), a separator line of ``$`` and the data: one record per
step ``u`` along the reference line, each the values of the ``D:`` channels in order. The
channels are long sections (heights in m at a lateral offset ``v``, left positive), and
optionally the reference line's heading ``phi`` (rad), its ``banking`` and ``slope`` (m/m).
Four data forms (the IPLOS formats of the OpenCRG user manual, ``../shared`` in the repo):

``LRFI`` / ``LDFI``
    Text: each record starts a new line, 8 numbers of 10 characters (``LRFI``) or 4 of 20
    (``LDFI``) per line; a field with a leading ``*`` is NaN.
``KRBI`` / ``KDBI``
    Binary after the separator line: big-endian IEEE float32 / float64, record after record
    with no break, padded with NaN to a whole number of 80 bytes.

:func:`read_crg` gives a :class:`CrgSurface`: heights ``z[iu, iv]`` on the ``(u, v)`` grid,
NaN margins kept as NaN, with the reference line's heading, banking and slope where the
file has them. The road's own heights are the long sections plus ``banking * v`` plus the
slope integrated along ``u`` (:meth:`CrgSurface.heights`). Every problem (truncated data,
wrong record length, a header that lies about the sizes, huge declared sizes, inf) is a
one-line :class:`~rough_map.errors.FileFormatError` naming the file and the field.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rough_map._bounded import clip
from rough_map._files import PathLike, atomic_output
from rough_map.errors import FileFormatError
from rough_map.io._check import check_readable
from rough_map.limits import LIMITS

__all__ = ["FORMATS", "CrgSurface", "read_crg", "write_crg"]

#: The data forms: bytes per binary number, or characters per text field and fields a line.
FORMATS = {"KRBI": (">f4", 0, 0), "KDBI": (">f8", 0, 0), "LRFI": ("", 10, 8), "LDFI": ("", 20, 4)}
_SEPARATOR = re.compile(rb"^\$\$\$\$[^\n]*\n", re.M)
_LONG_AT = re.compile(r"long section at v\s*=\s*([-+0-9.eE]+)", re.I)
_LONG_N = re.compile(r"long section\s+(\d+)", re.I)
_KEY = re.compile(r"^\s*([A-Za-z_]+)\s*=\s*([^!]*)")


@dataclass(frozen=True)
class CrgSurface:
    """A CRG road surface.

    Attributes
    ----------
    path : Path
        The file.
    u : ndarray, shape (nu,)
        Positions along the reference line, m.
    v : ndarray, shape (nv,)
        Lateral offsets of the long sections, m (left positive), increasing.
    z : ndarray, shape (nu, nv)
        Long-section heights in m relative to the reference line; NaN where unmeasured.
    phi : ndarray, shape (nu,), optional
        Heading of the reference line, rad (None: straight at ``start_phi``).
    banking, slope : ndarray, shape (nu,), optional
        Cross slope and longitudinal slope of the reference line, m/m.
    start : tuple of float
        ``(x, y, phi)`` of the reference line's start (m, m, rad).
    """

    path: Path
    u: np.ndarray
    v: np.ndarray
    z: np.ndarray
    phi: np.ndarray | None = None
    banking: np.ndarray | None = None
    slope: np.ndarray | None = None
    start: tuple[float, float, float] = (0.0, 0.0, 0.0)
    header: dict[str, float] = field(default_factory=dict, repr=False)

    @property
    def du(self) -> float:
        """Step along the reference line, m."""
        return float(self.u[1] - self.u[0]) if len(self.u) > 1 else math.nan

    @property
    def dv(self) -> float:
        """Step between long sections, m (NaN if they are not evenly spaced)."""
        steps = np.diff(self.v)
        if len(steps) and np.allclose(steps, steps[0], rtol=1e-6, atol=1e-9):
            return float(steps[0])
        return math.nan

    def reference_line(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(x, y, phi)`` of the reference line at each ``u`` (m, m, rad): from ``start``,
        each step of ``du`` runs along the mean of the headings at its two ends (straight
        at ``start``'s heading without a ``phi`` channel)."""
        x0, y0, phi0 = self.start
        n = len(self.u)
        phi = np.full(n, phi0) if self.phi is None else np.unwrap(np.nan_to_num(self.phi))
        mid = (phi[1:] + phi[:-1]) / 2
        du = self.du if n > 1 else 0.0
        x = x0 + np.concatenate([[0.0], np.cumsum(du * np.cos(mid))])
        y = y0 + np.concatenate([[0.0], np.cumsum(du * np.sin(mid))])
        return x, y, phi

    def node_xy(self) -> tuple[np.ndarray, np.ndarray]:
        """World ``(x, y)`` in m of every grid node, each shape ``(nu, nv)``: the reference
        line's point at ``u`` moved ``v`` to its left."""
        x, y, phi = self.reference_line()
        v = self.v[None, :]
        return x[:, None] - np.sin(phi)[:, None] * v, y[:, None] + np.cos(phi)[:, None] * v

    def heights(self) -> np.ndarray:
        """The road's heights in m on the ``(u, v)`` grid: the long sections plus the
        banking times ``v`` and the slope integrated along ``u``."""
        z = np.array(self.z, dtype=np.float64)
        if self.banking is not None:
            z += np.nan_to_num(self.banking)[:, None] * self.v[None, :]
        if self.slope is not None and len(self.u) > 1:
            s = np.nan_to_num(self.slope)
            rise = np.concatenate([[0.0], np.cumsum((s[1:] + s[:-1]) / 2 * np.diff(self.u))])
            z += rise[:, None]
        return z


def read_crg(path: PathLike) -> CrgSurface:
    """Read an OpenCRG file (text or binary data; see the module docstring).

    Raises
    ------
    FileFormatError
        Not a CRG file, a missing or bad parameter or channel, a data block that does not
        hold the records the header declares, huge declared sizes, an infinite value.
    """
    path = Path(path)
    check_readable(path)
    size = path.stat().st_size
    with path.open("rb") as fh:
        head = fh.read(min(size, LIMITS.document))
    found = _SEPARATOR.search(head)
    if found is None:
        target = _file_reference(head.decode("latin-1"))
        if target is not None:
            raise FileFormatError(
                path, f"refers to the CRG file {clip(target, 80)!r}: read that one", "header"
            )
        raise FileFormatError(path, "not an OpenCRG file: no $$$$ line before the data", "header")
    text = head[: found.start()].decode("latin-1")
    data_at = found.end()
    params, channels, form, u_channel = _parse_header(path, text)
    dtype, width, per_line = FORMATS[form]
    n_ch = len(channels)
    inc = params.get("REFERENCE_LINE_INCREMENT", u_channel[1] if u_channel else math.nan)
    u0 = params.get("REFERENCE_LINE_START_U", u_channel[0] if u_channel else 0.0)
    if not (math.isfinite(inc) and inc > 0):
        raise FileFormatError(
            path, f"REFERENCE_LINE_INCREMENT must be a step > 0 in m, got {inc}", "header"
        )
    declared = None
    if "REFERENCE_LINE_END_U" in params:
        declared = round((params["REFERENCE_LINE_END_U"] - u0) / inc) + 1
    with path.open("rb") as fh:
        fh.seek(data_at)
        raw = fh.read()
    if dtype:
        values = _binary(path, raw, dtype, n_ch, declared)
    else:
        values = _text(path, raw.decode("latin-1"), width, per_line, n_ch)
    n_u = values.shape[0]
    if np.isinf(values).any():
        row = int(np.argwhere(np.isinf(values))[0, 0])
        raise FileFormatError(path, f"an infinite value in record {row + 1}", field="data")
    if declared is not None:
        if declared != n_u:
            raise FileFormatError(
                path,
                f"the header declares {declared} records (u {u0:g} to "
                f"{params['REFERENCE_LINE_END_U']:g} by {inc:g} m); the data holds {n_u}",
                field="REFERENCE_LINE_END_U",
            )
    u = u0 + inc * np.arange(n_u)
    kinds = [kind for kind, _ in channels]
    sections = [i for i, kind in enumerate(kinds) if kind == "z"]
    if len(sections) < 2:
        raise FileFormatError(path, "fewer than 2 long sections", field="KD_Definition")
    v = np.array([_offset(path, channels[i][1], params, len(sections)) for i in sections])
    order = np.argsort(v)
    if np.any(np.diff(v[order]) <= 0):
        raise FileFormatError(path, "two long sections at the same v", field="KD_Definition")
    extra = {kind: values[:, kinds.index(kind)] for kind in ("phi", "banking", "slope")
             if kind in kinds}  # fmt: skip
    start = (
        params.get("REFERENCE_LINE_START_X", 0.0),
        params.get("REFERENCE_LINE_START_Y", 0.0),
        params.get("REFERENCE_LINE_START_PHI", 0.0),
    )
    return CrgSurface(
        path,
        u,
        v[order],
        values[:, sections][:, order],
        extra.get("phi"),
        extra.get("banking"),
        extra.get("slope"),
        start,
        params,
    )


def _file_reference(text: str) -> str | None:
    """The path a ``$ROAD_CRG_FILE`` section names, if the file has one."""
    lines = iter(text.splitlines())
    for line in lines:
        if line.upper().startswith("$ROAD_CRG_FILE"):
            for ref in lines:
                body = ref.split("!")[0].strip()
                if body.startswith("$"):
                    return None
                if body and not body.startswith(("*", "%")):
                    return body
    return None


def _parse_header(
    path: Path, text: str
) -> tuple[dict[str, float], list[tuple[str, str]], str, tuple[float, float] | None]:
    """The ``$ROAD_CRG`` parameters, the data channels (kind, definition), the data form
    and the virtual u channel's start and step."""
    params: dict[str, float] = {}
    channels: list[tuple[str, str]] = []
    form = "KRBI"
    u_channel = None
    section = ""
    for line in text.splitlines():
        if line.startswith("$"):
            name = line[1:].split("!")[0].strip().upper()
            section = name if name and not name.startswith("!") else ""
            continue
        if line.startswith(("*", "%")) or not line.strip():
            continue
        if section == "ROAD_CRG":
            m = _KEY.match(line)
            if m:
                params[m.group(1).upper()] = _number(path, m.group(2), m.group(1).upper())
        elif section == "KD_DEFINITION":
            body = line.split("!")[0].strip()
            if body.startswith("#:"):
                form = body[2:].strip().upper()
                if form not in FORMATS:
                    raise FileFormatError(
                        path, f"data form {clip(form, 20)!r} is not one of {sorted(FORMATS)}",
                        field="KD_Definition",
                    )  # fmt: skip
            elif body.upper().startswith("U:"):
                parts = body[2:].split(",")
                if len(parts) >= 4:
                    u_channel = (_number(path, parts[2], "U"), _number(path, parts[3], "U"))
            elif body.upper().startswith("D:"):
                channels.append((_kind(body[2:]), body[2:]))
                if len(channels) > LIMITS.model_features:
                    raise FileFormatError(path, "too many channels", field="KD_Definition")
    if not channels:
        raise FileFormatError(path, "no data channel (D:) defined", field="KD_Definition")
    return params, channels, form, u_channel


def _kind(definition: str) -> str:
    name = definition.split(",")[0].strip().lower()
    for kind in ("phi", "banking", "slope"):
        if name == f"reference line {kind}":
            return kind
    if name.startswith("long section"):
        return "z"
    return "other"


def _offset(path: Path, definition: str, params: dict[str, float], n: int) -> float:
    """The lateral offset in m of a long-section channel: as its name says (``long section
    at v = ...``), or the N-th of ``n`` from ``LONG_SECTION_V_RIGHT`` (default: the sections
    centred on the reference line) every ``LONG_SECTION_V_INCREMENT``."""
    m = _LONG_AT.search(definition)
    if m:
        return _number(path, m.group(1), "KD_Definition")
    m = _LONG_N.search(definition)
    inc = params.get("LONG_SECTION_V_INCREMENT")
    right = params.get("LONG_SECTION_V_RIGHT", -(n - 1) * inc / 2 if inc else None)
    if m and right is not None and inc is not None and inc > 0:
        return right + (int(m.group(1)) - 1) * inc
    raise FileFormatError(
        path,
        f"long section {clip(definition, 40)!r} has no v: name it 'long section at v = ...' "
        "or give LONG_SECTION_V_RIGHT and LONG_SECTION_V_INCREMENT",
        field="KD_Definition",
    )


def _number(path: Path, text: str, name: str) -> float:
    try:
        value = float(text.strip())
    except ValueError:
        raise FileFormatError(path, f"not a number: {clip(text.strip(), 30)!r}", name) from None
    if not math.isfinite(value):
        raise FileFormatError(path, f"not a finite number: {value}", field=name)
    return value


def _binary(
    path: Path, raw: bytes, dtype: str, n_ch: int, declared: int | None = None
) -> np.ndarray:
    """Records of ``n_ch`` big-endian numbers; the NaN padding to a whole 80 B is dropped.
    With the ``declared`` number of records (the header's), records all NaN at the end
    are data (a margin) when the header counts them; without it, they are padding."""
    item = np.dtype(dtype).itemsize
    if len(raw) % 80:
        raise FileFormatError(
            path,
            f"binary data of {len(raw)} B is not a whole number of 80 B blocks (truncated?)",
            field="data",
        )
    count = len(raw) // item
    if count > LIMITS.raster_cells:
        raise FileFormatError(path, f"{count} values: more than a grid holds", field="data")
    values = np.frombuffer(raw, dtype=dtype).astype(np.float64)
    pad = 80 // item
    if (
        declared is not None
        and 2 <= declared
        and 0 <= count - declared * n_ch < pad
        and np.isnan(values[declared * n_ch :]).all()
    ):
        return values[: declared * n_ch].reshape(declared, n_ch)
    n_u = count // n_ch
    # the padding is fewer than 80 B of NaN: drop whole records of it
    while n_u > 0 and count - (n_u - 1) * n_ch < pad and np.isnan(values[(n_u - 1) * n_ch :]).all():
        n_u -= 1
    if not np.isnan(values[n_u * n_ch :]).all() or count - n_u * n_ch >= pad + n_ch:
        raise FileFormatError(
            path,
            f"{count - n_u * n_ch} values after the last whole record of {n_ch} channels are "
            "not the NaN padding: wrong record length?",
            field="data",
        )
    if n_u < 2:
        raise FileFormatError(path, f"{n_u} records: a surface needs 2 or more", field="data")
    return values[: n_u * n_ch].reshape(n_u, n_ch)


def _text(path: Path, data: str, width: int, per_line: int, n_ch: int) -> np.ndarray:
    """Records of ``n_ch`` fixed-width fields, each record starting on a new line."""
    lines = [line.rstrip("\r\n") for line in data.splitlines() if line.strip()]
    lines_per_record = -(-n_ch // per_line)
    if len(lines) % lines_per_record:
        raise FileFormatError(
            path,
            f"{len(lines)} data lines are not whole records of {lines_per_record} lines "
            f"({n_ch} channels, {per_line} a line): wrong record length?",
            field="data",
        )
    n_u = len(lines) // lines_per_record
    if n_u * n_ch > LIMITS.raster_cells:
        raise FileFormatError(path, f"{n_u} records: more than a grid holds", field="data")
    if n_u < 2:
        raise FileFormatError(path, f"{n_u} records: a surface needs 2 or more", field="data")
    out = np.empty((n_u, n_ch))
    for r in range(n_u):
        fields: list[str] = []
        for line in lines[r * lines_per_record : (r + 1) * lines_per_record]:
            fields += [line[k : k + width] for k in range(0, len(line), width)]
        if len(fields) != n_ch:
            raise FileFormatError(
                path, f"record {r + 1} holds {len(fields)} fields, not {n_ch}", field="data"
            )
        for c, f in enumerate(fields):
            f = f.strip()
            if f.startswith("*"):
                out[r, c] = math.nan
                continue
            try:
                out[r, c] = float(f)
            except ValueError:
                raise FileFormatError(
                    path, f"record {r + 1}: not a number: {clip(f, 24)!r}", field="data"
                ) from None
    return out


def write_crg(
    path: PathLike,
    z: np.ndarray,
    du: float,
    v: np.ndarray,
    *,
    u0: float = 0.0,
    phi: np.ndarray | None = None,
    form: str = "KRBI",
    comment: str = "written by rough_map",
    start: tuple[float, float, float] | None = None,
) -> Path:
    """Write heights ``z[iu, iv]`` (m, NaN: unmeasured) every ``du`` m along a reference
    line from ``u0``, long sections at ``v`` (m, left positive), as an OpenCRG file in
    ``form`` (:data:`FORMATS`); ``phi`` (rad, one per record) makes the line curved;
    ``start`` is the line's ``(x, y, phi)`` in the world (m, m, rad). Written
    atomically."""
    z = np.asarray(z, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    if form not in FORMATS:
        raise ValueError(f"form must be one of {sorted(FORMATS)}, got {form!r}")
    columns = [z] if phi is None else [np.asarray(phi, dtype=np.float64)[:, None], z]
    data = np.hstack(columns)
    n_u = z.shape[0]
    head = [
        "$CT",
        comment,
        "$",
        "$ROAD_CRG",
        f"REFERENCE_LINE_START_U   = {float(u0)!r}",
        f"REFERENCE_LINE_END_U     = {float(u0 + (n_u - 1) * du)!r}",
        f"REFERENCE_LINE_INCREMENT = {float(du)!r}",
        *(
            []
            if start is None
            else [
                f"REFERENCE_LINE_START_X   = {float(start[0])!r}",
                f"REFERENCE_LINE_START_Y   = {float(start[1])!r}",
                f"REFERENCE_LINE_START_PHI = {float(start[2])!r}",
            ]
        ),
        "$",
        "$KD_Definition",
        f"#:{form}",
        *(["D:reference line phi,rad"] if phi is not None else []),
        *(f"D:long section at v = {float(x)!r},m" for x in v),
        "$",
        "$" * 72,
    ]
    dtype, width, per_line = FORMATS[form]
    path = Path(path)
    with atomic_output(path) as tmp, tmp.open("wb") as fh:
        fh.write(("\n".join(head) + "\n").encode("latin-1"))
        if dtype:
            flat = data.ravel()
            pad = -(flat.size * np.dtype(dtype).itemsize) % 80 // np.dtype(dtype).itemsize
            # big-endian on disk (concatenate would give the machine's order back)
            fh.write(np.concatenate([flat, np.full(pad, np.nan)]).astype(dtype).tobytes())
        else:
            for row in data:
                cells = [_field(x, width) for x in row]
                for k in range(0, len(cells), per_line):
                    fh.write(("".join(cells[k : k + per_line]) + "\n").encode("latin-1"))
    return path


def _field(x: float, width: int) -> str:
    """``x`` in ``width`` characters, as many digits as fit: fixed point for numbers of
    ordinary size, else scientific; NaN as the placeholder of stars."""
    if not math.isfinite(x):
        return "*" * width
    if abs(x) < 1e5:
        fixed = f"{x:{width}.{width - 2 - len(str(int(abs(x))))}f}"
        if len(fixed) == width and (x == 0 or abs(x) >= 10 ** -(width - 6)):
            return fixed
    return f"{x:{width}.{width - 8}e}"
