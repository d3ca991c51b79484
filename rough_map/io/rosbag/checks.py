"""Checks of a bag's structure before rosbags reads it.

rosbags trusts the sizes and counts a bag declares: a damaged record length makes it read
(allocate) up to 16 EiB, a hostile ``metadata.yaml`` makes it recurse, fail with a
``TypeError`` or open 20,000 files. :func:`check_bag` walks the records of the storage
files (ROS 1 ``.bag``, MCAP) and validates ``metadata.yaml`` first, with sizes checked
against the real file sizes, so that what rosbags then reads is bounded by the input.

The crash this walk prevents: rosbags (0.11) decompresses every chunk whole in memory, so a
chunk bomb (a valid bag of 1.3 MB whose lz4 chunk expands to 300 MiB took 300+ MiB more;
one of a hundred MB takes more than the machine has) ends in the kernel's OOM killer. The
walk finds every chunk and decompresses it in dropped 1 MiB steps against its declared size
and ``LIMITS.bag_chunk`` (``tests/test_library_crashes.py`` shows the blow-up). The checks
of ``metadata.yaml`` prevent hangs and escapes: a list of 20,000 storage files made rosbags
hang, a 500 kB list in one field took its YAML parser 16 s of CPU, and a path may leave the
bag folder (``tests/test_bag_hardening.py``). The record lengths and indices, checked on the
way, turn what rosbags raises late or as another error into one line naming the record;
they prevent no crash.

Every problem is a :class:`rough_map.errors.FileFormatError` naming the file and the
record or field.
"""

from __future__ import annotations

import functools
import struct
from pathlib import Path, PurePath
from typing import Any

from rough_map._bounded import short
from rough_map.errors import FileFormatError
from rough_map.limits import LIMITS

_MCAP_MAGIC = b"\x89MCAP0\r\n"
_ROS1_MAGIC = b"#ROSBAG V2.0\n"
_SQLITE_MAGIC = b"SQLite format 3\x00"
_MCAP_COMPRESSIONS = ("", "lz4", "zstd")
_ROS1_COMPRESSIONS = ("none", "bz2", "lz4")


def check_bag(path: Path) -> None:
    """Check the structure of a bag (file or ROS 2 folder) before rosbags opens it.

    Raises
    ------
    FileFormatError
        A size, count or field that does not fit the files.
    """
    if not path.is_dir() and not path.is_file():  # a FIFO or a device would never end
        raise FileFormatError(path, "not a bag: neither a regular file nor a folder")
    if path.is_dir():
        storage, files = check_metadata(path)
        for file in files:
            _check_storage_file(file, storage)
    elif path.suffix == ".bag":
        check_ros1(path)
    elif path.suffix == ".mcap":
        check_mcap(path)
    elif path.suffix == ".db3":
        check_sqlite(path)


def _check_storage_file(path: Path, storage: str) -> None:
    if storage == "mcap":
        check_mcap(path)
    else:
        check_sqlite(path)


# -- metadata.yaml ---------------------------------------------------------------------------


def check_metadata(folder: Path) -> tuple[str, list[Path]]:
    """Validate the ``metadata.yaml`` of a ROS 2 bag folder as rosbags uses it.

    Returns
    -------
    storage : str
        ``"mcap"`` or ``"sqlite3"``.
    files : list of Path
        The storage files, checked to be regular files inside ``folder``.

    Raises
    ------
    FileFormatError
        Missing, too large, too deep, not YAML, or a field of the wrong type or value.
    """
    path = folder / "metadata.yaml"
    if not path.is_file():
        raise FileFormatError(folder, "not a bag: no metadata.yaml in the folder")
    if path.stat().st_size > LIMITS.bag_metadata:
        raise FileFormatError(path, f"larger than {LIMITS.bag_metadata} bytes")
    try:
        text = path.read_bytes().decode("utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise FileFormatError(path, f"cannot read: {type(err).__name__}") from None
    storage, names = _metadata(str(path), text)
    return storage, _storage_files(path, folder, names)


@functools.lru_cache(maxsize=16)
def _metadata(name: str, text: str) -> tuple[str, tuple[Any, ...]]:
    """Storage and file names of a valid ``metadata.yaml`` text (cached: a bag is often
    opened more than once)."""
    from ruamel.yaml import YAML
    from ruamel.yaml.error import YAMLError

    path = Path(name)
    _check_depth(path, text)
    try:
        document = YAML(typ="safe").load(text)
    except (YAMLError, RecursionError, ValueError, TypeError) as err:
        raise FileFormatError(path, f"not valid YAML ({type(err).__name__})") from None
    info = _get(path, document, "rosbag2_bagfile_information", dict, "")
    where = "rosbag2_bagfile_information."
    version = _get(path, info, "version", int, where)
    if not 1 <= version <= 9:
        raise FileFormatError(path, f"unsupported version {_number(version)}", where + "version")
    storage = _get(path, info, "storage_identifier", str, where)
    if storage not in ("mcap", "sqlite3"):
        raise FileFormatError(
            path, f"unsupported storage {short(storage)}", where + "storage_identifier"
        )
    for key in ("compression_mode", "compression_format"):
        value = info.get(key)
        if value is not None and not isinstance(value, str):
            raise FileFormatError(path, "not a string", where + key)
    mode = (info.get("compression_mode") or "").lower()
    if mode not in ("", "none", "storage"):  # storage: compressed MCAP chunks, checked below
        raise FileFormatError(
            path,
            f"compressed bags (mode {short(mode)}) are not supported; decompress it first",
            where + "compression_mode",
        )
    for key, sub in (("duration", "nanoseconds"), ("starting_time", "nanoseconds_since_epoch")):
        _nanoseconds(path, _get(path, info, key, dict, where), sub, f"{where}{key}.")
    _nanoseconds(path, info, "message_count", where)
    files = info.get("files", [])
    if not isinstance(files, list) or len(files) > LIMITS.bag_storage_files:
        raise FileFormatError(
            path, f"not a list of at most {LIMITS.bag_storage_files} entries", where + "files"
        )
    for i, entry in enumerate(files):
        at = f"{where}files[{i}]."
        if not isinstance(entry, dict):
            raise FileFormatError(path, "not a mapping", at[:-1])
        name = _get(path, entry, "path", str, at)
        if len(name) > LIMITS.bag_name:
            raise FileFormatError(path, "too long", at + "path")
        for key, sub_key in (
            ("duration", "nanoseconds"),
            ("starting_time", "nanoseconds_since_epoch"),
        ):
            if key in entry:
                _nanoseconds(path, _get(path, entry, key, dict, at), sub_key, f"{at}{key}.")
        if "message_count" in entry:
            _nanoseconds(path, entry, "message_count", at)
    names = _get(path, info, "relative_file_paths", list, where)
    if not 1 <= len(names) <= LIMITS.bag_storage_files:
        raise FileFormatError(
            path,
            f"{len(names)} files listed (1 to {LIMITS.bag_storage_files} accepted)",
            where + "relative_file_paths",
        )
    topics = _get(path, info, "topics_with_message_count", list, where)
    if len(topics) > LIMITS.bag_topics:
        raise FileFormatError(
            path, f"{len(topics)} topics (at most {LIMITS.bag_topics})", where + "topics"
        )
    for i, topic in enumerate(topics):
        _check_topic(path, topic, f"{where}topics_with_message_count[{i}].")
    return storage, tuple(names)


def _check_depth(path: Path, text: str) -> None:
    """Refuse flow collections nested deeper than ``LIMITS.bag_metadata_depth`` (a cheap
    scan that counts brackets anywhere, quoted or not) and block nesting deeper than the same bound
    (indentation and "- " markers of a line)."""
    depth = deepest = 0
    for char in text:
        if char in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif char in "]}":
            depth -= 1
    if deepest > LIMITS.bag_metadata_depth:
        raise FileFormatError(path, f"nested deeper than {LIMITS.bag_metadata_depth} levels")
    for line in text.splitlines():
        stripped = line.lstrip(" -?:")
        if len(line) - len(stripped) > 4 * LIMITS.bag_metadata_depth:
            raise FileFormatError(path, f"nested deeper than {LIMITS.bag_metadata_depth} levels")


def _get(path: Path, mapping: Any, key: str, kind: type, where: str) -> Any:
    """``mapping[key]``, checked to be a ``kind`` (a bool is not an int)."""
    if not isinstance(mapping, dict):
        raise FileFormatError(path, "not a mapping", where.rstrip(".") or None)
    if key not in mapping:
        raise FileFormatError(path, "missing", where + key)
    value = mapping[key]
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise FileFormatError(
            path, f"expected {kind.__name__}, got {type(value).__name__}", where + key
        )
    if isinstance(value, str) and len(value) > LIMITS.bag_name:
        raise FileFormatError(path, f"longer than {LIMITS.bag_name} characters", where + key)
    return value


def _number(value: int) -> str:
    """An int of a file for a message: itself if short, else its size."""
    return str(value) if abs(value) < 10**20 else f"a {value.bit_length()}-bit number"


def _nanoseconds(path: Path, mapping: Any, key: str, where: str) -> int:
    value = _get(path, mapping, key, int, where)
    if not 0 <= value < 2**63:
        raise FileFormatError(path, f"{_number(value)} outside [0, 2**63)", where + key)
    return int(value)


def _storage_files(path: Path, folder: Path, names: tuple[Any, ...]) -> list[Path]:
    field = "rosbag2_bagfile_information.relative_file_paths"
    root = folder.resolve()
    files = []
    seen: set[str] = set()
    for i, name in enumerate(names):
        if not isinstance(name, str) or not 0 < len(name) <= LIMITS.bag_name:
            raise FileFormatError(path, f"not a file name: {short(name)}", f"{field}[{i}]")
        pure = PurePath(name)
        if pure.is_absolute() or ".." in pure.parts:
            raise FileFormatError(path, f"{short(name)} leaves the bag folder", f"{field}[{i}]")
        file = folder / pure.name  # where rosbags looks
        if pure.name in seen:
            raise FileFormatError(path, f"{short(name)} listed twice", f"{field}[{i}]")
        seen.add(pure.name)
        try:
            inside = file.resolve().parent == root and file.is_file()
        except (OSError, RuntimeError, ValueError):
            inside = False
        if not inside:
            raise FileFormatError(
                path, f"{short(name)} is not a file of the bag folder", f"{field}[{i}]"
            )
        files.append(file)
    return files


def _check_topic(path: Path, topic: Any, where: str) -> None:
    _nanoseconds(path, topic, "message_count", where)
    meta = _get(path, topic, "topic_metadata", dict, where)
    where += "topic_metadata."
    for key in ("name", "type", "serialization_format"):
        _get(path, meta, key, str, where)
    if "type_description_hash" in meta:
        _get(path, meta, "type_description_hash", str, where)
    qos = meta.get("offered_qos_profiles", [])
    if isinstance(qos, str):
        if len(qos) > LIMITS.bag_name * 16:
            raise FileFormatError(path, "too long", where + "offered_qos_profiles")
        _check_depth(path, qos)
    elif not isinstance(qos, list) or len(qos) > 1024 or not all(isinstance(q, dict) for q in qos):
        raise FileFormatError(path, "not a list of mappings", where + "offered_qos_profiles")


# -- storage files -----------------------------------------------------------------------------


def check_sqlite(path: Path) -> None:
    """A ``.db3`` must start with the SQLite header (sqlite itself checks the rest)."""
    with _open(path) as f:
        if f.read(16) != _SQLITE_MAGIC:
            raise _corrupt(path, "not an SQLite file (bad header)")


def _open(path: Path) -> Any:
    try:
        return path.open("rb")
    except OSError as err:
        raise FileFormatError(path, f"cannot open: {err.strerror}") from None


def _corrupt(path: Path, message: str, field: str | None = None) -> FileFormatError:
    """The error of a storage file whose structure does not hold."""
    return FileFormatError(path, f"cannot read the bag: {message} (truncated or corrupt?)", field)


def _bounded_decompress(path: Path, data: bytes, compression: str, size: int, where: str) -> None:
    """Check that compressed ``data`` gives exactly ``size`` bytes (at most
    ``LIMITS.bag_chunk``), decompressing it in steps of 1 MiB that are dropped at once: a
    decompression bomb costs time bounded by ``size``, and no memory."""
    if size > LIMITS.bag_chunk:
        raise _corrupt(path, f"chunk declares {size} B (at most {LIMITS.bag_chunk})", where)
    try:
        total = _decompressed_size(data, compression, size)
    except Exception as err:  # each library has its own error types
        raise _corrupt(
            path, f"undecodable {compression} chunk ({type(err).__name__})", where
        ) from None
    if total != size:
        more = "more than " if total > size else ""
        raise _corrupt(path, f"chunk decompresses to {more}{total} B, not {size}", where)


def _decompressor(compression: str) -> Any:
    if compression == "bz2":
        import bz2

        return bz2.BZ2Decompressor()
    if compression == "lz4":
        from lz4.frame import LZ4FrameDecompressor

        return LZ4FrameDecompressor()
    try:
        from compression import zstd
    except ImportError:
        from backports import zstd
    return zstd.ZstdDecompressor()


def _decompressed_size(data: bytes, compression: str, size: int) -> int:
    """Bytes that ``data`` (one or more concatenated streams) decompresses to, counted up
    to ``size + 1``."""
    step = 1 << 20
    total = 0
    while data and total <= size:
        decompressor = _decompressor(compression)
        total += len(decompressor.decompress(data, max_length=step))
        while not decompressor.eof and total <= size:
            if decompressor.needs_input:
                raise EOFError("truncated stream")
            total += len(decompressor.decompress(b"", max_length=step))
        data = decompressor.unused_data
    return total


def check_mcap(path: Path) -> None:
    """Walk the records of an MCAP file: every length must fit the file, every chunk its
    record, and the chunk index of the summary must point at those chunks.

    Raises
    ------
    FileFormatError
        Bad magic, a record or chunk running past its end, a bad chunk index.
    """
    with _open(path) as f:
        size = f.seek(0, 2)
        if size < 8 + 9 + 37:
            raise _corrupt(path, f"too short for an MCAP file ({size} B)")
        f.seek(0)
        if f.read(8) != _MCAP_MAGIC:
            raise _corrupt(path, "not an MCAP file (bad magic)")
        f.seek(size - 37)
        footer = f.read(37)
        if footer[:9] != b"\x02\x14" + bytes(7) or footer[-8:] != _MCAP_MAGIC:
            raise _corrupt(path, "bad MCAP footer")
        (summary_start,) = struct.unpack_from("<Q", footer, 9)
        chunks: dict[int, tuple[int, str, int]] = {}
        index: list[tuple[int, int, str, int, int]] = []
        offsets = set()
        pos, end = 8, size - 37
        while pos < end:
            f.seek(pos)
            head = f.read(9)
            if len(head) < 9:
                raise _corrupt(path, f"truncated record at byte {pos}")
            op, length = head[0], struct.unpack_from("<Q", head, 1)[0]
            if length > end - pos - 9:
                raise _corrupt(
                    path, f"record at byte {pos} declares {length} B past the end", "mcap"
                )
            offsets.add(pos)
            if op == 0x06:
                chunks[pos] = _mcap_chunk(path, f, pos, length)
            elif op == 0x08:
                index.append(_mcap_chunk_index(path, f.read(length), pos))
            pos += 9 + length
        if pos != end:
            raise _corrupt(path, "records overrun the footer", "mcap")
        if summary_start and summary_start not in offsets:
            raise _corrupt(path, f"summary offset {summary_start} is not a record")
        for at, chunk_start, compression, compressed, uncompressed in index:
            if chunks.get(chunk_start) != (compressed, compression, uncompressed):
                raise _corrupt(path, f"chunk index at byte {at} does not match a chunk", "mcap")


def _mcap_chunk(path: Path, f: Any, pos: int, length: int) -> tuple[int, str, int]:
    """(compressed size, compression, uncompressed size) of the chunk record at ``pos``."""
    where = "mcap chunk"
    if length < 40:
        raise _corrupt(path, f"chunk at byte {pos} too short ({length} B)", where)
    head = f.read(32)
    uncompressed = struct.unpack_from("<Q", head, 16)[0]
    (name_length,) = struct.unpack_from("<I", head, 28)
    if name_length > 16 or 40 + name_length > length:
        raise _corrupt(path, f"chunk at byte {pos}: bad compression name", where)
    compression = f.read(name_length).decode("latin-1")
    (compressed,) = struct.unpack("<Q", f.read(8))
    if compressed > length - 40 - name_length:
        raise _corrupt(path, f"chunk at byte {pos} overruns its record", where)
    if compression not in _MCAP_COMPRESSIONS:
        raise _corrupt(
            path, f"chunk at byte {pos}: unknown compression {short(compression)}", where
        )
    if compression == "":
        if uncompressed != compressed:
            raise _corrupt(path, f"chunk at byte {pos}: sizes differ", where)
    else:
        _bounded_decompress(path, f.read(compressed), compression, uncompressed, where)
    return compressed, compression, uncompressed


def _mcap_chunk_index(path: Path, record: bytes, pos: int) -> tuple[int, int, str, int, int]:
    """(record offset, chunk offset, compression, compressed and uncompressed sizes) of a
    chunk index record."""
    try:
        chunk_start = struct.unpack_from("<Q", record, 16)[0]
        (n,) = struct.unpack_from("<I", record, 32)
        at = 36 + n + 8
        (name_length,) = struct.unpack_from("<I", record, at)
        compression = record[at + 4 : at + 4 + name_length].decode("latin-1")
        compressed, uncompressed = struct.unpack_from("<QQ", record, at + 4 + name_length)
    except struct.error:
        raise _corrupt(path, f"truncated chunk index at byte {pos}", "mcap") from None
    return pos, chunk_start, compression, compressed, uncompressed


# -- ROS 1 -------------------------------------------------------------------------------------


def check_ros1(path: Path) -> None:
    """Walk the records of a ROS 1 bag: every header and data length must fit the file;
    index records must have the layout rosbags reads, chunk infos must point at chunks
    followed by their index records.

    Raises
    ------
    FileFormatError
        Bad magic, a record running past the end, a bad header, chunk or index.
    """
    with _open(path) as f:
        size = f.seek(0, 2)
        f.seek(0)
        if f.read(len(_ROS1_MAGIC)) != _ROS1_MAGIC:
            raise _corrupt(path, "not a ROS 1 bag V2.0 (bad magic)")
        records: list[tuple[int, int]] = []  # (offset, op)
        chunk_infos: list[tuple[int, int, int]] = []  # (offset, chunk_pos, connections)
        index_layout: bytes | None = None
        pos = len(_ROS1_MAGIC)
        while pos < size:
            f.seek(pos)
            header, data_length = _ros1_record(path, f, pos, size)
            fields = _ros1_header(path, header, pos)
            op = fields.get("op", b"")
            if len(op) != 1:
                raise _corrupt(path, f"record at byte {pos} has no op", "ros1 header")
            records.append((pos, op[0]))
            if op[0] == 0x04:
                index_layout = _ros1_index(path, header, fields, data_length, pos, index_layout)
            elif op[0] == 0x05:
                _ros1_chunk(path, f, fields, data_length, pos)
            elif op[0] == 0x06:
                chunk_infos.append(_ros1_chunk_info(path, f, fields, data_length, pos))
            elif op[0] == 0x03:
                _ros1_bag_header(path, fields, size, pos)
            pos += 8 + len(header) + data_length
    starts = {offset: i for i, (offset, _) in enumerate(records)}
    for at, chunk_pos, n in chunk_infos:
        i = starts.get(chunk_pos)
        following = [op for _, op in records[i + 1 : i + 1 + n]] if i is not None else []
        if i is None or records[i][1] != 0x05 or following != [0x04] * n:
            raise _corrupt(
                path, f"chunk info at byte {at} does not point at an indexed chunk", "ros1"
            )


def _ros1_record(path: Path, f: Any, pos: int, size: int) -> tuple[bytes, int]:
    head = f.read(4)
    if len(head) < 4:
        raise _corrupt(path, f"truncated record at byte {pos}", "ros1")
    (header_length,) = struct.unpack("<I", head)
    if header_length > size - pos - 8:
        raise _corrupt(path, f"record header at byte {pos} runs past the end", "ros1")
    header = f.read(header_length)
    (data_length,) = struct.unpack("<I", f.read(4))
    if data_length > size - pos - 8 - header_length:
        raise _corrupt(path, f"record data at byte {pos} runs past the end", "ros1")
    return header, data_length


def _ros1_header(path: Path, header: bytes, pos: int) -> dict[str, bytes]:
    fields: dict[str, bytes] = {}
    at = 0
    while at < len(header):
        if at + 4 > len(header):
            raise _corrupt(path, f"bad header at byte {pos}", "ros1 header")
        (length,) = struct.unpack_from("<I", header, at)
        field = header[at + 4 : at + 4 + length]
        name, sep, value = field.partition(b"=")
        if len(field) != length or not sep:
            raise _corrupt(path, f"bad header field at byte {pos}", "ros1 header")
        fields[name.decode("latin-1")] = value
        at += 4 + length
    return fields


def _uint(path: Path, fields: dict[str, bytes], name: str, width: int, pos: int) -> int:
    value = fields.get(name, b"")
    if len(value) != width:
        raise _corrupt(path, f"record at byte {pos}: bad field {name!r}", "ros1 header")
    return int.from_bytes(value, "little")


def _ros1_bag_header(path: Path, fields: dict[str, bytes], size: int, pos: int) -> None:
    if _uint(path, fields, "index_pos", 8, pos) > size:
        raise _corrupt(path, "index_pos past the end of the bag", "ros1 header")


def _ros1_index(
    path: Path,
    header: bytes,
    fields: dict[str, bytes],
    data_length: int,
    pos: int,
    layout: bytes | None,
) -> bytes:
    """An index data record: rosbags reads each one with the field layout of the first."""
    names = b"".join(sorted(n.encode("latin-1") for n in fields))
    ok = (
        len(header) == 47
        and names == b"conncountopver"
        and _uint(path, fields, "ver", 4, pos) == 1
        and data_length == 12 * _uint(path, fields, "count", 4, pos)
        and len(fields["conn"]) == 4
    )
    order = _field_order(header)
    if not ok or (layout is not None and order != layout):
        raise _corrupt(path, f"bad index record at byte {pos}", "ros1 index")
    return order


def _field_order(header: bytes) -> bytes:
    """The names of a header's fields in their order, joined by commas."""
    names, at = [], 0
    while at + 4 <= len(header):
        (length,) = struct.unpack_from("<I", header, at)
        names.append(header[at + 4 : at + 4 + length].partition(b"=")[0])
        at += 4 + length
    return b",".join(names)


def _ros1_chunk(path: Path, f: Any, fields: dict[str, bytes], data_length: int, pos: int) -> None:
    compression = fields.get("compression", b"").decode("latin-1")
    if compression not in _ROS1_COMPRESSIONS:
        raise _corrupt(
            path, f"chunk at byte {pos}: unknown compression {short(compression)}", "ros1 chunk"
        )
    if compression != "none":
        size = _uint(path, fields, "size", 4, pos)
        _bounded_decompress(path, f.read(data_length), compression, size, "ros1 chunk")


def _ros1_chunk_info(
    path: Path, f: Any, fields: dict[str, bytes], data_length: int, pos: int
) -> tuple[int, int, int]:
    count = _uint(path, fields, "count", 4, pos)
    if _uint(path, fields, "ver", 4, pos) != 1 or data_length != 8 * count:
        raise _corrupt(path, f"bad chunk info at byte {pos}", "ros1 chunk info")
    data = f.read(data_length)
    connections = {data[i : i + 4] for i in range(0, data_length, 8)}
    return pos, _uint(path, fields, "chunk_pos", 8, pos), len(connections)
