"""Opening ROS 1 and ROS 2 bags with rosbags, listing their topics, reading one topic.

Every error of rosbags and its storage backends on a damaged or foreign bag is raised as a
:class:`rough_map.errors.FileFormatError` naming the bag (and the topic concerned).
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rough_map._files import PathLike
from rough_map.errors import FileFormatError

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

    errors: list[type[BaseException]] = [AnyReaderError, Reader1Error, Reader2Error, SerdeError]
    try:  # the sqlite3 storage of rosbags goes through apsw
        import apsw

        errors.append(apsw.Error)
    except ImportError:
        pass
    return tuple(errors)


# What garbage bytes make the parsers of rosbags raise (a size read from a damaged record,
# a seek past the end, ...). Caught only around calls into rosbags, never around our code.
_CORRUPT_DATA_ERRORS = (struct.error, EOFError, OverflowError, ValueError, IndexError, KeyError)


def _read_errors() -> tuple[type[BaseException], ...]:
    return (*_rosbags_errors(), *_CORRUPT_DATA_ERRORS)


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
    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except FileNotFoundError as err:
        raise FileFormatError(path, f"not a bag: {err}") from err
    except _read_errors() as err:
        raise FileFormatError(path, f"cannot read the bag (truncated or corrupt?): {err}") from err
    try:
        yield reader
    except _rosbags_errors() as err:
        raise FileFormatError(path, f"damaged bag (truncated or corrupt?): {err}") from err
    finally:
        reader.close()


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
    if not found:
        available = ", ".join(sorted({c.topic for c in reader.connections})) or "none"
        raise FileFormatError(
            path, f"no topic {topic!r} in the bag; available topics: {available}", field=topic
        )
    wrong = sorted({c.msgtype for c in found if c.msgtype != msgtype})
    if wrong:
        raise FileFormatError(
            path, f"topic {topic!r} carries {', '.join(wrong)}, expected {msgtype}", field=topic
        )
    return found


def raw_messages(
    reader: AnyReader, path: Path, connections: list[Any]
) -> Iterator[tuple[Any, int, bytes]]:
    """``reader.messages(connections)``, with damaged-bag errors as FileFormatError."""
    messages = reader.messages(connections)
    errors = _read_errors()
    while True:
        try:
            item = next(messages)
        except StopIteration:
            return
        except errors as err:
            raise FileFormatError(path, f"damaged bag (truncated or corrupt?): {err!r}") from err
        yield item


def deserialize(reader: AnyReader, path: Path, connection: Any, raw: bytes) -> Any:
    """The message of ``raw`` bytes of ``connection``; undecodable bytes as FileFormatError."""
    try:
        return reader.deserialize(raw, connection.msgtype)
    except _read_errors() as err:
        raise FileFormatError(
            path, f"undecodable {connection.msgtype} message: {err!r}", field=connection.topic
        ) from err


def topic_messages(
    reader: AnyReader, path: Path, topic: str, msgtype: str
) -> Iterator[tuple[int, Any]]:
    """(receive time in ns, deserialized message) of one topic, in receive order."""
    connections = topic_connections(reader, path, topic, msgtype)
    for connection, t_ns, raw in raw_messages(reader, path, connections):
        yield t_ns, deserialize(reader, path, connection, raw)
