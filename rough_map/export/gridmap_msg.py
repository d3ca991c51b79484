"""A map as ROS 2 ``grid_map_msgs/msg/GridMap`` messages in an MCAP bag (rosbags), for RViz
and Foxglove: one per update of the map as it grew, then the whole map.

The message definitions are those of grid_map's ROS 2 packages, registered in a rosbags
typestore with :func:`rosbags.typesys.get_types_from_msg` (no ROS install needed). Each
layer is a ``std_msgs/Float32MultiArray`` in grid_map's layout: the matrix of shape
``(n_x, n_y)`` of :func:`rough_map.map.grid.to_grid_map` (index (0, 0) at the largest x and
y), stored column-major (``layout.dim[0]`` is ``column_index``), NaN unknown, start
indices 0.
"""

from __future__ import annotations

import logging
import math
import os
import tempfile
from collections.abc import Iterable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rough_map.errors import FileFormatError, InputError
from rough_map.export.costmap import OCCUPANCY_GRID, occupancy_grid_message
from rough_map.io.rosbag.checks import check_bag
from rough_map.io.rosbag.reader import available_topics, read_errors, topic_field, why
from rough_map.map.grid import GridMap, GridMapData, to_grid_map

log = logging.getLogger(__name__)

__all__ = [
    "COSTMAP_TOPIC",
    "GRID_MAP",
    "GRID_MAP_INFO",
    "grid_map_message",
    "grid_map_typestore",
    "message_to_grid_map",
    "read_gridmap_bag",
    "write_gridmap_bag",
]

GRID_MAP = "grid_map_msgs/msg/GridMap"
GRID_MAP_INFO = "grid_map_msgs/msg/GridMapInfo"

#: grid_map_msgs/msg/GridMapInfo (ROS 2).
GRID_MAP_INFO_MSG = """\
# Resolution of the grid [m/cell].
float64 resolution
# Length in x-direction [m].
float64 length_x
# Length in y-direction [m].
float64 length_y
# Pose of the grid map center in the frame defined in `header` [m].
geometry_msgs/Pose pose
"""

#: grid_map_msgs/msg/GridMap (ROS 2).
GRID_MAP_MSG = """\
# Header (time and frame)
std_msgs/Header header
# Grid map header
grid_map_msgs/GridMapInfo info
# Grid map layer names.
string[] layers
# Grid map basic layer names (optional).
string[] basic_layers
# Grid map data.
std_msgs/Float32MultiArray[] data
# Row start index (default 0).
uint16 outer_start_index
# Column start index (default 0).
uint16 inner_start_index
"""

#: Default topic of the map.
TOPIC = "/rough_map/grid_map"
#: Topic of the costmap (``nav_msgs/msg/OccupancyGrid``) a bag of a map with a vehicle holds.
COSTMAP_TOPIC = "/rough_map/costmap"


def grid_map_typestore(store: Any = None) -> Any:
    """A rosbags typestore (default: ROS 2 Humble) that knows the grid_map messages."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = store or get_typestore(Stores.ROS2_HUMBLE)
    if GRID_MAP not in store.types:
        types = get_types_from_msg(GRID_MAP_INFO_MSG, GRID_MAP_INFO)
        types.update(get_types_from_msg(GRID_MAP_MSG, GRID_MAP))
        store.register(types)
    return store


def grid_map_message(data: GridMapData, typestore: Any, *, stamp_ns: int = 0) -> Any:
    """A ``grid_map_msgs/msg/GridMap`` message of a map in grid_map's conventions.

    Parameters
    ----------
    data : GridMapData
        The map (:func:`rough_map.map.grid.to_grid_map`).
    typestore : rosbags Typestore
        From :func:`grid_map_typestore`.
    stamp_ns : int
        Header stamp, ns since the epoch.
    """
    t = typestore.types
    nx, ny = data.size
    dims = [
        t["std_msgs/msg/MultiArrayDimension"](label="column_index", size=ny, stride=nx * ny),
        t["std_msgs/msg/MultiArrayDimension"](label="row_index", size=nx, stride=nx),
    ]
    arrays = [
        t["std_msgs/msg/Float32MultiArray"](
            layout=t["std_msgs/msg/MultiArrayLayout"](dim=dims, data_offset=0),
            data=np.asarray(m, dtype=np.float32).ravel(order="F"),
        )
        for m in data.layers.values()
    ]
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=data.position[0], y=data.position[1], z=0.0),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
    )
    header = t["std_msgs/msg/Header"](
        stamp=t["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9),
        frame_id=data.frame_id,
    )
    info = t[GRID_MAP_INFO](
        resolution=data.resolution, length_x=data.length[0], length_y=data.length[1], pose=pose
    )
    return t[GRID_MAP](
        header=header,
        info=info,
        layers=list(data.layers),
        basic_layers=list(data.basic_layers),
        data=arrays,
        outer_start_index=0,
        inner_start_index=0,
    )


def message_to_grid_map(msg: Any) -> GridMapData:
    """The :class:`~rough_map.map.grid.GridMapData` of a deserialized GridMap message.

    Raises
    ------
    InputError
        A resolution that is not finite and positive, lengths that are not finite or give
        a grid beyond 2**31 cells a side, layer names and data arrays that do not pair up,
        a layer whose size is not ``n_x * n_y``, or a start index other than 0.
    """
    info = msg.info
    res = float(info.resolution)
    length = (float(info.length_x), float(info.length_y))
    position = (float(info.pose.position.x), float(info.pose.position.y))
    if not (math.isfinite(res) and res > 0):
        raise InputError(f"resolution {res!r} m is not a finite positive number")
    if not all(math.isfinite(v) and v >= 0 for v in length):
        raise InputError(f"lengths {length!r} m are not finite and >= 0")
    if not all(math.isfinite(v) for v in position):
        raise InputError(f"position {position!r} m is not finite")
    cells = [v / res for v in length]
    if not all(c < 2**31 for c in cells):
        raise InputError(f"lengths {length!r} m at {res!r} m give more than 2**31 cells a side")
    nx, ny = round(cells[0]), round(cells[1])
    if msg.outer_start_index or msg.inner_start_index:
        raise InputError("circularly shifted grid maps (start index != 0) are not supported")
    if len(msg.layers) != len(msg.data):
        raise InputError(f"{len(msg.layers)} layer names for {len(msg.data)} data arrays")
    if not msg.data and nx * ny > 2**24:
        raise InputError(f"a grid of {nx} x {ny} cells without any layer")
    layers = {}
    for name, arr in zip(msg.layers, msg.data, strict=True):
        size = len(arr.data)
        if size != nx * ny:
            label = name if name.isprintable() and len(name) <= 30 else repr(name)[:30]
            raise InputError(f"layer {label!r} has {size} values; expected {nx} x {ny}")
        values = np.asarray(arr.data, dtype=np.float64)
        row_major = bool(arr.layout.dim) and arr.layout.dim[0].label == "row_index"
        layers[name] = values.reshape(nx, ny) if row_major else values.reshape(ny, nx).T
    return GridMapData(
        frame_id=msg.header.frame_id,
        resolution=res,
        position=position,
        length=length,
        layers=layers,
        basic_layers=tuple(msg.basic_layers),
    )


def _stamp(t: float, after: int) -> int:
    """``t`` s as ns since the epoch, never before ``after`` (NaN: ``after``)."""
    if not math.isfinite(t):
        return after
    return max(after, int(round(max(t, 0.0) * 1e9)))


def write_gridmap_bag(
    grid: GridMap,
    path: str | Path,
    *,
    topic: str = TOPIC,
    layers: list[str] | tuple[str, ...] | None = None,
    stamp_ns: int | None = None,
    updates: Iterable[tuple[float, GridMap]] = (),
    basic_layers: tuple[str, ...] = ("R",),
    occupancy: NDArray[np.int8] | None = None,
) -> Path:
    """Write a map as GridMap messages in a ROS 2 bag with MCAP storage: one per update of
    the map as it grew, then the whole map.

    Parameters
    ----------
    grid : GridMap
        The map.
    path : str or Path
        The bag folder to write (replaced if it exists; its parent must exist).
    topic : str
        Topic of the messages.
    layers : sequence of str, optional
        Layers to publish (default: every layer that is not internal).
    stamp_ns : int, optional
        Time of the whole map's message, ns since the epoch (default: the latest
        ``last_seen`` of the map, else 0; never before the last update).
    updates : iterable of (float, GridMap)
        The map around each update as it then stood, with its time in s
        (:meth:`rough_map.online.OnlineMapper.replay`): one message each, before the whole
        map, so that a viewer replays how the map grew (RViz's grid_map display with a
        history length keeps the earlier ones on screen). Their layers are those of
        ``layers`` that the window has (``elevation`` is not replayed).
    basic_layers : tuple of str
        grid_map's basic layers (a cell is valid where they are all known), those of them
        that each message has.
    occupancy : ndarray of int8, optional
        The map's costs (:func:`rough_map.export.costmap.cost_layer`): also one
        ``nav_msgs/msg/OccupancyGrid`` on :data:`COSTMAP_TOPIC`, stamped as the whole map.

    Returns
    -------
    Path
        ``path``.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer

    path = Path(path)
    if not path.parent.is_dir():
        raise FileFormatError(path, f"cannot write: folder {path.parent} does not exist")
    names = list(layers) if layers is not None else None
    store = grid_map_typestore()
    count, last = 0, 0
    with tempfile.TemporaryDirectory(dir=path.parent, prefix=f".{path.name}.") as tmp:
        staged = Path(tmp) / path.name
        with Writer(staged, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            conn = writer.add_connection(topic, GRID_MAP, typestore=store)
            for t, window in updates:
                shown = [n for n in (names or grid.layers) if n in window.layers]
                shown = [n for n in shown if window.info(n).kind != "internal" and n != "elevation"]
                basic = tuple(b for b in basic_layers if b in shown)
                last = _stamp(t, last)
                msg = grid_map_message(to_grid_map(window, shown, basic), store, stamp_ns=last)
                writer.write(conn, last, store.serialize_cdr(msg, GRID_MAP))
                count += 1
            if stamp_ns is None:
                seen = grid["last_seen"] if "last_seen" in grid else np.array([np.nan])
                latest = float(np.nanmax(seen)) if np.any(np.isfinite(seen)) else math.nan
                stamp_ns = _stamp(latest, last)
            data = to_grid_map(grid, names)
            basic = tuple(b for b in basic_layers if b in data.layers)
            msg = grid_map_message(replace(data, basic_layers=basic), store, stamp_ns=stamp_ns)
            writer.write(conn, stamp_ns, store.serialize_cdr(msg, GRID_MAP))
            if occupancy is not None:
                costs = writer.add_connection(COSTMAP_TOPIC, OCCUPANCY_GRID, typestore=store)
                grid_msg = occupancy_grid_message(grid, occupancy, store, stamp_ns=stamp_ns)
                writer.write(costs, stamp_ns, store.serialize_cdr(grid_msg, OCCUPANCY_GRID))
        if path.exists():
            old = Path(tmp) / "replaced"
            os.replace(path, old)
        os.replace(staged, path)
    log.info("wrote %s (%d update(s) and the whole map, %s on %s)", path, count, GRID_MAP, topic)
    return path


def read_gridmap_bag(path: str | Path, topic: str | None = None) -> list[GridMapData]:
    """The GridMap messages of a ROS 2 bag, in time order.

    Parameters
    ----------
    path : str or Path
        The bag folder (or its ``.mcap``/``.db3`` file).
    topic : str, optional
        Only this topic (default: every GridMap connection).

    Raises
    ------
    FileFormatError
        The bag is missing, truncated or corrupt; ``topic`` carries no GridMap (the
        message lists the available topics); a message is undecodable or inconsistent
        (its index and topic are named).
    """
    from rosbags.rosbag2 import Reader

    path = Path(path)
    if not path.exists():
        raise FileFormatError(path, "no such bag")
    check_bag(path)
    store = grid_map_typestore()
    maps = []
    try:
        with Reader(path) as reader:
            conns = [
                c
                for c in reader.connections
                if c.msgtype == GRID_MAP and (topic is None or c.topic == topic)
            ]
            if not conns:
                if topic is None:
                    return []
                raise FileFormatError(
                    path,
                    f"no {GRID_MAP} on {topic_field(topic)}; available topics: "
                    f"{available_topics({c.topic for c in reader.connections})}",
                    field=topic_field(topic),
                )
            for index, (conn, _, raw) in enumerate(reader.messages(connections=conns)):
                maps.append(_grid_map_of(path, store, conn.topic, index, raw))
    except FileFormatError:
        raise
    except read_errors() as err:
        raise FileFormatError(
            path, f"could not read grid maps (truncated or corrupt?): {why(err)}"
        ) from None
    return maps


def _grid_map_of(path: Path, store: Any, topic: str, index: int, raw: bytes) -> GridMapData:
    """The map of message ``index`` (raw CDR bytes) of ``topic``."""

    try:
        msg = store.deserialize_cdr(raw, GRID_MAP)
    except read_errors() as err:
        raise FileFormatError(
            path, f"undecodable GridMap message {index}: {why(err)}", field=topic_field(topic)
        ) from None
    try:
        return message_to_grid_map(msg)
    except InputError as err:
        raise FileFormatError(path, f"message {index}: {err}", field=topic_field(topic)) from None
