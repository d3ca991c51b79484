"""Grid map: a geometry (resolution, origin, size, CRS) plus named float layers.

The geometry is :class:`rough_map.map.grid_geometry.GridGeometry` (re-exported here); this
module holds the layers (:class:`GridMap`) and the conversion to grid_map's conventions.

Conventions
-----------
* **World frame**: x east (or local x), y north (or local y), metres, as everywhere in
  rough_map (:mod:`rough_map.types`). The CRS of the map says what "world" means
  (:class:`rough_map.config.Crs`).
* **Geometry**: ``resolution`` is the side of a square cell in m. ``origin`` is the world
  (x, y) in m of the *south-west corner* of the map, i.e. the lower-left corner of cell
  ``[0, 0]``. ``shape`` is ``(n_rows, n_cols)``. Maps built by rough_map keep ``origin`` on
  the lattice ``k * resolution`` (k integer), so cell edges of maps of the same resolution
  line up, and growing a map only ever adds whole cells.
* **Axis order**: layers are arrays indexed ``[row, col]``. The row index increases
  northwards (+y), the column index eastwards (+x): row 0 is the *southern* edge of the map
  (plot with ``imshow(..., origin="lower")``). The centre of cell ``[i, j]`` is at
  ``(origin_x + (j + 0.5) * resolution, origin_y + (i + 0.5) * resolution)``. This is the
  order of :class:`rough_map.types.HeightField` (whose ``origin`` is the centre of cell
  ``[0, 0]``: see :meth:`GridMap.to_height_field`). GeoTIFF export flips the rows so that
  files are north-up.
* **Layers** are float64 arrays of the map's shape; NaN means unknown. Each layer carries
  its units and a description (:class:`LayerInfo`). Accumulator layers that fusion keeps
  (sums, Dirichlet evidence) are ``kind="internal"`` and are not exported.

grid_map (ANYbotics) conventions, for :func:`to_grid_map` / :func:`from_grid_map`
-------------------------------------------------------------------------------------
``position`` is the map centre in the frame (m), ``length`` is ``(length_x, length_y)`` in
m, the data matrix has shape ``(n_x, n_y)``, its index ``(0, 0)`` is the cell with the
largest x and largest y, the row index increases along -x and the column index along -y.
Exported maps have no circular-buffer shift (start index ``(0, 0)``). Hence
``grid_map_matrix = layer[::-1, ::-1].T`` and ``layer = grid_map_matrix.T[::-1, ::-1]``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rough_map.config import Crs
from rough_map.errors import InputError
from rough_map.map.grid_geometry import GridGeometry
from rough_map.types import HeightField

log = logging.getLogger(__name__)

__all__ = [
    "GridGeometry",
    "GridMap",
    "GridMapData",
    "LayerInfo",
    "from_grid_map",
    "to_grid_map",
]

#: Default margin in m added around the area a map has to cover when it is (re)allocated.
DEFAULT_MARGIN = 2.0

LayerKind = Literal["value", "class", "internal"]


@dataclass(frozen=True)
class LayerInfo:
    """What a layer holds.

    Attributes
    ----------
    units : str
        Units of the values (``"m^3/rad"``, ``"1"`` for dimensionless, ``"s"``, ...).
    description : str
        One line saying what the layer is.
    fill : float
        Value of cells nothing has written (NaN: unknown; 0 for counts and sums).
    kind : {"value", "class", "internal"}
        ``"class"``: indices into ``categories`` (NaN unknown); ``"internal"``: a fusion
        accumulator, not exported.
    categories : tuple of str
        Names of the values 0, 1, ... of a class (or level) layer.
    """

    units: str
    description: str = ""
    fill: float = math.nan
    kind: LayerKind = "value"
    categories: tuple[str, ...] = ()


class GridMap:
    """A grid geometry plus named float layers (NaN: unknown).

    Parameters
    ----------
    geometry : GridGeometry
        Where the map lies.
    attrs : mapping, optional
        Free metadata (class names, traverse name, ...); kept through growth and copies.

    Examples
    --------
    >>> g = GridMap(GridGeometry(0.1, (0.0, 0.0), (20, 30)))
    >>> _ = g.add_layer("R", units="m^3/rad", description="overall energy")
    >>> g["R"].shape
    (20, 30)
    """

    def __init__(self, geometry: GridGeometry, *, attrs: Mapping[str, Any] | None = None):
        self._geometry = geometry
        self._data: dict[str, NDArray[np.float64]] = {}
        self._info: dict[str, LayerInfo] = {}
        self.attrs: dict[str, Any] = dict(attrs or {})
        # layers made together by add_layers_as: their block, and each one's index in it
        self._block: NDArray[np.float64] | None = None
        self._slots: dict[str, int] = {}

    def __getstate__(self) -> dict[str, Any]:
        # The block is storage, not state: a copy or a pickle holds each layer as an array
        # of its own (they would no longer be views of the block it held).
        return {**self.__dict__, "_block": None, "_slots": {}}

    def __repr__(self) -> str:
        g = self._geometry
        return (
            f"GridMap(shape={g.shape}, resolution={g.resolution} m, origin={g.origin}, "
            f"crs={g.crs.code}, layers={list(self._data)})"
        )

    # -- geometry -----------------------------------------------------------------------

    @property
    def geometry(self) -> GridGeometry:
        """The map's :class:`GridGeometry`."""
        return self._geometry

    @property
    def shape(self) -> tuple[int, int]:
        """``(n_rows, n_cols)`` of every layer."""
        return self._geometry.shape

    @property
    def resolution(self) -> float:
        """Cell size in m."""
        return self._geometry.resolution

    @property
    def crs(self) -> Crs:
        """CRS of the world frame."""
        return self._geometry.crs

    # -- layers -------------------------------------------------------------------------

    @property
    def layers(self) -> tuple[str, ...]:
        """Names of the layers, in creation order."""
        return tuple(self._data)

    def __contains__(self, name: object) -> bool:
        return name in self._data

    def __iter__(self) -> Iterator[str]:
        return iter(self._data)

    def add_layer(
        self,
        name: str,
        *,
        units: str,
        description: str = "",
        fill: float = math.nan,
        kind: LayerKind = "value",
        categories: tuple[str, ...] = (),
        data: ArrayLike | None = None,
    ) -> NDArray[np.float64]:
        """Create layer ``name`` (filled with ``fill``, or ``data``) and return its array.

        Parameters
        ----------
        name : str
            Layer name; must be new.
        units, description, fill, kind, categories
            See :class:`LayerInfo`.
        data : array_like, optional
            Initial values, broadcast to the map's shape.
        """
        if not name or not isinstance(name, str):
            raise InputError(f"a layer name must be a non-empty string, got {name!r}")
        if name in self._data:
            raise InputError(f"layer {name!r} exists already")
        if kind not in ("value", "class", "internal"):
            raise InputError(f"kind must be 'value', 'class' or 'internal', got {kind!r}")
        arr = np.full(self.shape, fill, dtype=np.float64)
        if data is not None:
            arr[...] = self._check_shape(name, data)
        self._data[name] = arr
        self._info[name] = LayerInfo(units, description, float(fill), kind, tuple(categories))
        return arr

    def add_layer_as(self, name: str, info: LayerInfo, data: ArrayLike | None = None) -> None:
        """Create layer ``name`` as ``info`` describes it (filled with its fill, or
        ``data``), e.g. a layer of another map."""
        self.add_layer(
            name,
            units=info.units,
            description=info.description,
            fill=info.fill,
            kind=info.kind,
            categories=info.categories,
            data=data,
        )

    def add_layers_as(self, layers: Sequence[tuple[str, LayerInfo]]) -> None:
        """Create the layers ``(name, info)``, each filled with its fill, in one block of
        memory: what :meth:`add_layer_as` does one by one, for the few dozen accumulators
        of every map tile (a tile of an hour's map is made a thousand times)."""
        seen = set(self._data)
        for name, info in layers:
            if not name or not isinstance(name, str) or not isinstance(info, LayerInfo):
                raise InputError(f"layers must be (name, LayerInfo) pairs, got {name!r}")
            if name in seen:
                raise InputError(f"layer {name!r} exists already")
            seen.add(name)
        block = np.empty((len(layers), *self.shape))
        block[...] = np.array([info.fill for _, info in layers])[:, None, None]
        for (name, info), arr in zip(layers, block, strict=True):
            self._data[name] = arr
            self._info[name] = info
        if self._block is None:
            self._block = block
            self._slots = {name: i for i, (name, _) in enumerate(layers)}

    def add_at(self, cells: NDArray[np.intp], sums: Sequence[tuple[str, float]]) -> None:
        """Add ``value`` to layer ``name`` in ``cells`` (distinct indices into the flat
        layer), for each ``(name, value)`` of ``sums``; names the map lacks are skipped.
        What fusion does for every patch: the layers made by :meth:`add_layers_as` take
        their values in one step (a name given twice gets both values)."""
        if len({name for name, _ in sums}) < len(sums):
            for name, value in sums:
                self.add_at(cells, [(name, value)])
            return
        rows, values = [], []
        for name, value in sums:
            slot = self._slots.get(name)
            if slot is not None:
                rows.append(slot)
                values.append(value)
            elif name in self._data:
                self._data[name].reshape(-1)[cells] += value
        if rows and self._block is not None:
            flat = self._block.reshape(len(self._block), -1)
            flat[np.array(rows)[:, None], cells] += np.array(values)[:, None]

    def __getitem__(self, name: str) -> NDArray[np.float64]:
        """The array of layer ``name``, shape :attr:`shape`, in the layer's units
        (:meth:`units`); a view that writes go through to."""
        try:
            return self._data[name]
        except KeyError:
            raise InputError(
                f"no layer {name!r}; the map has {list(self._data) or 'no layers'}"
            ) from None

    def __setitem__(self, name: str, value: ArrayLike) -> None:
        """Overwrite existing layer ``name`` with ``value`` (broadcast)."""
        self[name][...] = self._check_shape(name, value)

    def _check_shape(self, name: str, value: ArrayLike) -> NDArray[np.float64]:
        arr = np.asarray(value, dtype=np.float64)
        try:
            np.broadcast_to(arr, self.shape)
        except ValueError:
            raise InputError(
                f"layer {name!r}: values of shape {arr.shape} do not fit a map of shape "
                f"{self.shape}"
            ) from None
        return arr

    def info(self, name: str) -> LayerInfo:
        """The :class:`LayerInfo` (units, description, ...) of layer ``name``."""
        self[name]
        return self._info[name]

    def units(self, name: str) -> str:
        """Units of layer ``name``."""
        return self.info(name).units

    def drop_layer(self, name: str) -> None:
        """Remove layer ``name``."""
        self[name]
        del self._data[name], self._info[name]
        self._slots.pop(name, None)

    # -- growth -------------------------------------------------------------------------

    def ensure_covers(
        self, bounds: tuple[float, float, float, float], *, margin: float = DEFAULT_MARGIN
    ) -> tuple[int, int]:
        """Grow the map (reallocating every layer) so that it covers ``bounds``.

        New cells hold each layer's fill value; existing cells keep their world position
        and values. The origin stays on the map's lattice.

        Parameters
        ----------
        bounds : tuple of float
            ``(xmin, ymin, xmax, ymax)`` in m.
        margin : float
            Extra room in m on the sides that grow, so that a map following a vehicle is
            not reallocated at every step.

        Returns
        -------
        tuple of int
            ``(rows, cols)`` added on the south and west sides (indices of existing cells
            shift by this much); ``(0, 0)`` if the map did not grow southwards or westwards.
        """
        geometry, (di, dj) = self._geometry.grown_to_cover(bounds, margin)
        if geometry is self._geometry:
            return 0, 0
        rows, cols = self.shape
        self._block, self._slots = None, {}  # every layer gets an array of its own
        for name, old in self._data.items():
            new = np.full(geometry.shape, self._info[name].fill, dtype=np.float64)
            new[di : di + rows, dj : dj + cols] = old
            self._data[name] = new
        log.debug("map grown from %s to %s cells", self.shape, geometry.shape)
        self._geometry = geometry
        return di, dj

    def cells_at(
        self, x: ArrayLike, y: ArrayLike, *, grow: bool = True, margin: float = DEFAULT_MARGIN
    ) -> NDArray[np.int64]:
        """Cell indices ``(N, 2)`` as ``(row, col)`` of world points (x, y) in m.

        With ``grow`` the map first grows to hold every point (earlier indices may then
        shift: see :meth:`ensure_covers`); without it, points outside raise.
        """
        xa, ya = np.broadcast_arrays(np.asarray(x, float).ravel(), np.asarray(y, float).ravel())
        if not (np.all(np.isfinite(xa)) and np.all(np.isfinite(ya))):
            raise InputError("x and y must be finite positions in m")
        if grow and xa.size:
            self.ensure_covers((xa.min(), ya.min(), xa.max(), ya.max()), margin=margin)
        rows, cols = self._geometry.cell_of(xa, ya)
        if not np.all(self._geometry.inside(rows, cols)):
            raise InputError("some points lie outside the map; pass grow=True")
        return np.column_stack([rows, cols])

    # -- conversions --------------------------------------------------------------------

    def copy(self) -> GridMap:
        """A deep copy."""
        out = GridMap(self._geometry, attrs=self.attrs)
        out._data = {k: v.copy() for k, v in self._data.items()}
        out._info = dict(self._info)
        return out

    def shallow_copy(self) -> GridMap:
        """A new map holding the same arrays (a write into a layer shows in both; layers
        added or dropped, in one only)."""
        out = GridMap(self._geometry, attrs=self.attrs)
        out._data = dict(self._data)
        out._info = dict(self._info)
        return out

    def to_height_field(self, layer: str) -> HeightField:
        """Layer ``layer`` as a :class:`rough_map.types.HeightField` (same axis order;
        its origin is the centre of cell ``[0, 0]``), e.g. for bilinear sampling."""
        res = self.resolution
        x0, y0 = self._geometry.origin
        return HeightField(self[layer].copy(), res, (x0 + res / 2, y0 + res / 2))


# ------------------------------------------------------------------------------------------
# grid_map (ANYbotics) conventions
# ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class GridMapData:
    """A map in grid_map's conventions (what a ``grid_map_msgs/GridMap`` carries).

    Attributes
    ----------
    frame_id : str
        Frame of ``position``.
    resolution : float
        Cell size in m.
    position : tuple of float
        World (x, y) in m of the map centre.
    length : tuple of float
        ``(length_x, length_y)`` in m.
    layers : dict of str to ndarray
        Each of shape ``(n_x, n_y)``; index ``(0, 0)`` is the cell with the largest x and
        largest y, rows go along -x, columns along -y; NaN unknown.
    basic_layers : tuple of str
        Layers that must be valid for a cell to be valid.
    """

    frame_id: str
    resolution: float
    position: tuple[float, float]
    length: tuple[float, float]
    layers: dict[str, NDArray[np.float64]]
    basic_layers: tuple[str, ...] = ()

    @property
    def size(self) -> tuple[int, int]:
        """``(n_x, n_y)``: grid_map's size (rows, columns of each matrix)."""
        return (
            int(round(self.length[0] / self.resolution)),
            int(round(self.length[1] / self.resolution)),
        )


def to_grid_map(
    grid: GridMap,
    layers: tuple[str, ...] | list[str] | None = None,
    basic_layers: tuple[str, ...] = (),
) -> GridMapData:
    """Convert a map to grid_map's conventions.

    Parameters
    ----------
    grid : GridMap
        The map.
    layers : sequence of str, optional
        Layers to take (default: every layer that is not ``kind="internal"``).
    basic_layers : tuple of str
        grid_map's basic layers.

    Returns
    -------
    GridMapData
        ``layers[name] = grid[name][::-1, ::-1].T`` (copies).
    """
    if layers is None:
        layers = [n for n in grid.layers if grid.info(n).kind != "internal"]
    g = grid.geometry
    return GridMapData(
        frame_id=g.frame_id,
        resolution=g.resolution,
        position=g.center,
        length=g.length,
        layers={n: np.ascontiguousarray(grid[n][::-1, ::-1].T) for n in layers},
        basic_layers=tuple(basic_layers),
    )


def from_grid_map(
    data: GridMapData,
    *,
    crs: Any = None,
    info: Mapping[str, LayerInfo] | None = None,
) -> GridMap:
    """Build a :class:`GridMap` from grid_map's conventions (inverse of
    :func:`to_grid_map`).

    Parameters
    ----------
    data : GridMapData
        The map; every layer of shape ``size``.
    crs : optional
        CRS of the frame (anything :meth:`Crs.from_any` reads).
    info : mapping of str to LayerInfo, optional
        Units and descriptions of the layers (default: unknown units ``""``).
    """
    nx, ny = data.size
    lx, ly = data.length
    if not (math.isclose(nx * data.resolution, lx) and math.isclose(ny * data.resolution, ly)):
        raise InputError(
            f"length {data.length} m is not a whole number of {data.resolution} m cells"
        )
    origin = (data.position[0] - lx / 2, data.position[1] - ly / 2)
    geometry = GridGeometry(data.resolution, origin, (ny, nx), Crs.from_any(crs), data.frame_id)
    grid = GridMap(geometry)
    info = info or {}
    for name, matrix in data.layers.items():
        m = np.asarray(matrix, dtype=np.float64)
        if m.shape != (nx, ny):
            raise InputError(f"layer {name!r} has shape {m.shape}; grid_map size is {(nx, ny)}")
        grid.add_layer_as(name, info.get(name, LayerInfo("")), m.T[::-1, ::-1])
    return grid
