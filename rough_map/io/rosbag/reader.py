"""Opening ROS 1 and ROS 2 bags with rosbags, listing their topics, reading one topic.

Every error of rosbags and its storage backends on a damaged or foreign bag is raised as a
:class:`rough_map.errors.FileFormatError` naming the bag (and the topic concerned), in one
line. The structure of the bag is checked first (:func:`~.checks.check_bag`) so that rosbags
never reads more than the files hold.
"""

from __future__ import annotations

import functools
import sqlite3
import struct
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rough_map._bounded import short
from rough_map._files import PathLike
from rough_map.errors import FileFormatError
from rough_map.io.rosbag.checks import check_bag
from rough_map.io.rosbag.writer import ros_typestore

if TYPE_CHECKING:
    from rosbags.highlevel import AnyReader


@dataclass(frozen=True)
class TopicInfo:
    """A topic of a bag: name, message type (``pkg/msg/Type``) and message count."""

    name: str
    msgtype: str
    count: int


@dataclass(frozen=True)
class BagInfo:
    """Summary of a bag.

    Attributes
    ----------
    path : Path
        The bag.
    topics : tuple of TopicInfo
        Sorted by name.
    start, end : float
        Receive time of the first and last message, s since the Unix epoch.
    message_count : int
        Messages on all topics.
    """

    path: Path
    topics: tuple[TopicInfo, ...]
    start: float
    end: float
    message_count: int

    @property
    def duration(self) -> float:
        """Time from the first to the last message, s."""
        return self.end - self.start


def _rosbags_errors() -> tuple[type[BaseException], ...]:
    """What rosbags and its storage backends raise on a damaged or foreign bag."""
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as Reader1Error
    from rosbags.rosbag2 import ReaderError as Reader2Error
    from rosbags.serde import SerdeError

    errors: list[type[BaseException]] = [
        AnyReaderError,
        Reader1Error,
        Reader2Error,
        SerdeError,
        sqlite3.Error,
    ]
    try:  # the sqlite3 storage of rosbags goes through apsw
        import apsw

        errors.append(apsw.Error)
    except ImportError:
        pass
    return tuple(errors)


# What garbage bytes make the parsers of rosbags raise (a size read from a damaged record,
# a seek past the end, an ``assert`` on a field, a message definition nested without end,
# ``ord()`` of an empty read...). Caught only around calls into rosbags, never around our
# code. Sizes are checked before (:mod:`.checks`), so no MemoryError is expected.
_CORRUPT_DATA_ERRORS = (
    struct.error,
    EOFError,
    OverflowError,
    ValueError,
    IndexError,
    KeyError,
    TypeError,
    AttributeError,
    AssertionError,
    RecursionError,
    OSError,
    SyntaxError,  # the code rosbags generates for a type whose name a bag mangled
)


def read_errors() -> tuple[type[BaseException], ...]:
    """What rosbags raises on damaged data: its own errors and those of garbage bytes."""
    return (*_rosbags_errors(), *_CORRUPT_DATA_ERRORS)


def why(err: BaseException) -> str:
    """One short line about an error of rosbags: its type and its text, quoted and cut."""
    return f"{type(err).__name__}: {short(str(err), 70)}"


@contextmanager
def open_bag(path: PathLike) -> Iterator[AnyReader]:
    """Open a ROS 1 or ROS 2 bag for reading.

    Errors of rosbags and its storage backends inside the ``with`` block (damaged chunks
    met while iterating, undecodable messages) are raised as :class:`FileFormatError`.

    Parameters
    ----------
    path : str or PathLike
        A ``.bag`` file, a ROS 2 bag folder, or a ``.db3``/``.mcap`` file.

    Yields
    ------
    rosbags.highlevel.AnyReader
        The open reader.

    Raises
    ------
    FileFormatError
        The bag does not exist, is empty, truncated or corrupt.
    """
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    if not path.exists():
        raise FileFormatError(path, "no such bag")
    if path.is_file() and path.stat().st_size == 0:
        raise FileFormatError(path, "the bag is empty (0 bytes)")
    check_bag(path)
    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except FileNotFoundError as err:
        raise FileFormatError(path, f"not a bag: {why(err)}") from err
    except read_errors() as err:
        raise FileFormatError(
            path, f"cannot read the bag (truncated or corrupt?): {why(err)}"
        ) from err
    try:
        yield reader
    except _rosbags_errors() as err:
        raise FileFormatError(path, f"damaged bag (truncated or corrupt?): {why(err)}") from err
    finally:
        try:
            reader.close()
        except read_errors():  # closing a reader left broken by damaged data
            pass


def inspect_bag(path: PathLike) -> BagInfo:
    """List the topics of a bag with their message types and counts.

    Parameters
    ----------
    path : str or PathLike
        A ``.bag`` file, a ROS 2 bag folder, or a ``.db3``/``.mcap`` file.

    Returns
    -------
    BagInfo
        Topics (name, type, count), time span in s and message count.

    Raises
    ------
    FileFormatError
        The bag cannot be read.
    """
    path = Path(path)
    with open_bag(path) as reader:
        topics = tuple(
            TopicInfo(name, info.msgtype or "(mixed types)", info.msgcount)
            for name, info in sorted(reader.topics.items())
        )
        count = reader.message_count
        start, end = (reader.start_time, reader.end_time) if count else (0, 0)
    if count:
        end = max(start, end - 1)  # rosbags' end_time is one ns past the last message
    return BagInfo(path, topics, start * 1e-9, end * 1e-9, count)


def topic_connections(reader: AnyReader, path: Path, topic: str, msgtype: str) -> list[Any]:
    """The connections of ``topic``, checked to carry ``msgtype``.

    Raises
    ------
    FileFormatError
        No such topic (the message lists the available ones), or another message type.
    """
    found = [c for c in reader.connections if c.topic == topic]
    field = topic_field(topic)
    if not found:
        raise FileFormatError(
            path,
            f"no topic {short(topic, 30)} in the bag; available topics: "
            f"{available_topics({c.topic for c in reader.connections})}",
            field=field,
        )
    wrong = sorted({c.msgtype for c in found if c.msgtype != msgtype})
    if wrong:
        carries = ", ".join(topic_field(w, 40) for w in wrong[:3]) + (", ..." * (len(wrong) > 3))
        raise FileFormatError(
            path, f"topic {short(topic, 30)} carries {carries}, expected {msgtype}", field=field
        )
    if reader.typestore.fielddefs.get(msgtype) is not None:
        bag_layout = _layout(reader.typestore, msgtype)
        if bag_layout != _reference_layout(not reader.is2, msgtype):
            raise FileFormatError(
                path, f"the bag defines {msgtype} with other fields than ROS does", field=field
            )
    return found


def available_topics(topics: set[str], limit: int = 60) -> str:
    """Sorted topic names for a message: at most ``limit`` characters, "none" if empty."""
    names = sorted(topics)
    text = ""
    for i, name in enumerate(names):
        item = topic_field(name, 30)
        if len(text) + len(item) + 2 > limit:
            return f"{text}, ... ({len(names) - i} more)"
        text += (", " if text else "") + item
    return text or "none"


def topic_field(topic: str, limit: int = 30) -> str:
    """A topic name as it can appear in a message: as is if short and printable, else
    quoted and cut to ``limit`` characters."""
    topic = str(topic)
    return topic if topic.isprintable() and len(topic) <= limit else short(topic, limit)


def _layout(store: Any, msgtype: str) -> Any:
    """The fields of ``msgtype`` in a typestore, nested types expanded (constants and
    string bounds left out): what the deserialized message looks like. Each type is
    expanded once and nesting stops at 16 levels, whatever a bag defines."""
    memo: dict[str, Any] = {}

    def layout(name: str, depth: int) -> Any:
        if name not in store.fielddefs or depth > 16:
            return name
        if name not in memo:
            _, fields = store.fielddefs[name]
            memo[name] = tuple((field, describe(desc, depth)) for field, desc in fields)
        return memo[name]

    def describe(desc: Any, depth: int) -> Any:
        kind, rest = desc
        if kind.name == "BASE":
            return rest[0]
        if kind.name == "NAME":
            return layout(rest, depth + 1)
        sub, count = rest
        return (kind.name, describe(sub, depth), count if kind.name == "ARRAY" else 0)

    return layout(msgtype, 0)


@functools.lru_cache(maxsize=32)
def _reference_layout(ros1: bool, msgtype: str) -> Any:

    store = ros_typestore(ros1)
    return _layout(store, msgtype) if msgtype in store.fielddefs else None


def raw_messages(
    reader: AnyReader, path: Path, connections: list[Any]
) -> Iterator[tuple[Any, int, bytes]]:
    """``reader.messages(connections)``, with damaged-bag errors as FileFormatError."""
    messages = reader.messages(connections)
    errors = read_errors()
    while True:
        try:
            item = next(messages)
        except StopIteration:
            return
        except errors as err:
            raise FileFormatError(path, f"damaged bag (truncated or corrupt?): {why(err)}") from err
        yield item


def deserialize(
    reader: AnyReader, path: Path, connection: Any, raw: bytes, index: int | None = None
) -> Any:
    """The message of ``raw`` bytes of ``connection`` (message ``index`` of its topic);
    undecodable bytes as FileFormatError."""
    try:
        return reader.deserialize(raw, connection.msgtype)
    except read_errors() as err:
        which = "" if index is None else f" {index}"
        raise FileFormatError(
            path,
            f"undecodable {connection.msgtype} message{which}: {why(err)}",
            field=topic_field(connection.topic),
        ) from err


def topic_messages(
    reader: AnyReader, path: Path, topic: str, msgtype: str
) -> Iterator[tuple[int, Any]]:
    """(receive time in ns, deserialized message) of one topic, in receive order."""
    connections = topic_connections(reader, path, topic, msgtype)
    for index, (connection, t_ns, raw) in enumerate(raw_messages(reader, path, connections)):
        yield t_ns, deserialize(reader, path, connection, raw, index)
