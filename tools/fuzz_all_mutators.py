"""Seeded mutators of :mod:`fuzz_all` (independent of ``tests/fuzzing.py``).

Every mutator takes the bytes of a valid file and a ``random.Random`` and returns new bytes;
the same ``(data, seed)`` always gives the same output. Byte mutators know nothing of the
format; the structure-aware ones parse JSON, YAML, NPY, ZIP (NPZ, skops) and PNG and break
one field: a wrong type, a huge count, deep nesting, a missing key, a YAML alias bomb or a
tag that would run code (it writes the file ``CODE_RAN`` in the case folder if it ever does).
"""

from __future__ import annotations

import io
import json
import math
import random
import re
import struct
import zipfile
import zlib
from collections.abc import Callable
from typing import Any

Mutator = Callable[[bytes, random.Random], bytes]

#: The file a YAML ``!!python/object`` tag writes, should a loader ever build Python objects.
CODE_MARKER = "CODE_RAN"

HOSTILE_NUMBERS = [
    b"0",
    b"-1",
    b"-0",
    b"1e999",
    b"-1e999",
    b"nan",
    b"NaN",
    b"inf",
    b"1e-320",
    b"4294967296",
    b"18446744073709551616",
    b"9" * 40,
    b"2147483648",
    b"0x7f",
    b"1.5",
    b"",
    b"1e308",
    b"-9223372036854775809",
    b"00000000000000000001",
    b"\xff",
]
HOSTILE_WORDS = {
    1: [0xFF, 0x80, 0x7F, 0],
    2: [0xFFFF, 0x8000, 0x7FFF, 0],
    4: [0xFFFFFFFF, 0x7FFFFFFF, 0x80000000, 0, 1, 0x10000000],
    8: [2**64 - 1, 2**63 - 1, 2**63, 2**40, 0, 0x7FF0000000000000, 0x7FF8000000000000],
}
HOSTILE_VALUES: list[Any] = [
    None,
    True,
    False,
    0,
    -1,
    2**70,
    -(2**70),
    1e308,
    -1e308,
    1e-320,
    "",
    "x",
    "A" * 5000,
    "../../../../etc/passwd",
    "/etc/passwd",
    "\x00\x01\x1b[31m",
    "nan",
    "inf",
    [],
    {},
    [1, 2],
    {"a": 1},
    [None] * 3,
    ["a"] * 2000,
    "é" * 10,
    3.5,
]
MAX_OUT = 8 << 20  # no mutated file grows beyond 8 MB


# --------------------------------------------------------------------------- bytes


def truncate(data: bytes, rng: random.Random) -> bytes:
    n = len(data)
    return data[: rng.choice((0, 1, n // 2, n - 1 if n else 0, rng.randrange(n + 1)))]


def flip_bits(data: bytes, rng: random.Random) -> bytes:
    out = bytearray(data)
    for _ in range(rng.randint(1, 16) if out else 0):
        out[rng.randrange(len(out))] ^= 1 << rng.randrange(8)
    return bytes(out)


def set_run(data: bytes, rng: random.Random) -> bytes:
    if not data:
        return data
    out = bytearray(data)
    i, n = rng.randrange(len(out)), rng.randint(1, 128)
    fill = rng.choice((b"\x00", b"\xff", None))
    run = rng.randbytes(n) if fill is None else fill * n
    out[i : i + n] = run[: max(0, min(n, len(out) - i))]
    return bytes(out)


def insert(data: bytes, rng: random.Random) -> bytes:
    i = rng.randrange(len(data) + 1)
    chunk = rng.choice(
        (
            rng.randbytes(rng.randint(1, 256)),
            b"\xff" * 64,
            b"\x00" * 64,
            b"\n" * 1000,
            b"\r\n",
            b"\x1b[2J",
        )
    )
    return data[:i] + chunk + data[i:]


def delete(data: bytes, rng: random.Random) -> bytes:
    if not data:
        return data
    i = rng.randrange(len(data))
    return data[:i] + data[i + rng.randint(1, 512) :]


def repeat(data: bytes, rng: random.Random) -> bytes:
    if not data:
        return data
    i = rng.randrange(len(data))
    chunk = data[i : i + rng.randint(1, 4096)]
    times = rng.randint(2, 64)
    return (data[:i] + chunk * times + data[i:])[:MAX_OUT]


def word(data: bytes, rng: random.Random) -> bytes:
    """A 1-8 byte integer (little or big endian) becomes a hostile value; mostly in the
    first 4 KB, where headers and counts are."""
    if not data:
        return data
    width = rng.choice((1, 2, 4, 4, 8, 8))
    span = min(len(data), 4096) if rng.random() < 0.7 else len(data)
    i = rng.randrange(span)
    if rng.random() < 0.5:
        i -= i % width
    value = rng.choice(HOSTILE_WORDS[width])
    raw = value.to_bytes(width, rng.choice(("little", "big")))
    return data[:i] + raw + data[i + width :]


def number_text(data: bytes, rng: random.Random) -> bytes:
    """A number written as text (a header count, a YAML value) becomes a hostile one."""
    numbers = list(re.finditer(rb"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?", data[:65536]))
    if not numbers:
        return flip_bits(data, rng)
    m = rng.choice(numbers)
    return data[: m.start()] + rng.choice(HOSTILE_NUMBERS) + data[m.end() :]


def garbage(data: bytes, rng: random.Random) -> bytes:
    return rng.choice(
        (
            b"",
            b"\x00",
            rng.randbytes(rng.randint(1, 2048)),
            b"\xff" * 4096,
            data[:16] + rng.randbytes(64),
        )
    )


def text_line(data: bytes, rng: random.Random) -> bytes:
    """A text line is dropped, doubled, cut, or gets a hostile token."""
    lines = data.split(b"\n")
    i = rng.randrange(len(lines))
    kind = rng.randrange(4)
    if kind == 0:
        del lines[i]
    elif kind == 1:
        lines[i : i + 1] = [lines[i]] * rng.randint(2, 200)
    elif kind == 2:
        lines[i] = lines[i][: rng.randrange(len(lines[i]) + 1)]
    else:
        lines[i] += b" " + rng.choice(HOSTILE_NUMBERS + [b"abc", b"\x00", b"\xe9\xff"])
    return b"\n".join(lines)[:MAX_OUT]


BYTE_MUTATORS: list[Mutator] = [
    truncate,
    flip_bits,
    set_run,
    insert,
    delete,
    repeat,
    word,
    word,
    number_text,
    garbage,
]


def bytes_mutation(data: bytes, rng: random.Random) -> bytes:
    """One to three stacked byte mutations."""
    for _ in range(rng.choice((1, 1, 1, 2, 3))):
        data = rng.choice(BYTE_MUTATORS)(data, rng)
    return data


# --------------------------------------------------------------------------- JSON / YAML


def _paths(node: Any, prefix: tuple = ()) -> list[tuple]:
    out = [prefix]
    if isinstance(node, dict):
        for k, v in node.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node[:20]):
            out += _paths(v, (*prefix, i))
    return out


_DEEP = "@@DEEP@@"


def _tree_mutation(doc: Any, rng: random.Random) -> Any:
    paths = [p for p in _paths(doc) if p]
    if not paths:
        return rng.choice(HOSTILE_VALUES + [_DEEP])
    path = rng.choice(paths)
    parent = doc
    for key in path[:-1]:
        parent = parent[key]
    key = path[-1]
    kind = rng.randrange(7)
    if kind == 0 and isinstance(parent, dict):
        del parent[key]
    elif kind == 1 and isinstance(parent, list):
        parent[key : key + 1] = [parent[key]] * rng.choice((0, 2, 1000, 20000))
    elif kind == 2:
        parent[key] = _DEEP
    elif kind == 3 and isinstance(parent, dict):
        parent[rng.choice(("x-unknown", "", "__class__", "A" * 300))] = parent.pop(key)
    elif kind == 4:
        parent[key] = rng.choice([[0.0] * rng.choice((0, 1, 100000)), {"k": parent[key]}])
    else:
        parent[key] = rng.choice(HOSTILE_VALUES)
    return doc


def json_mutation(data: bytes, rng: random.Random) -> bytes:
    try:
        doc = json.loads(data)
    except ValueError:
        return bytes_mutation(data, rng)
    if rng.random() < 0.15:  # top level of the wrong type, or deep nesting
        return rng.choice(
            (
                b"[]",
                b"null",
                b'"x"',
                b"1e999",
                b"[" * 100000 + b"]" * 100000,
                b'{"a":' * 50000 + b"1" + b"}" * 50000,
            )
        )
    doc = _tree_mutation(doc, rng)
    text = json.dumps(doc, allow_nan=True)
    depth = rng.choice((100, 1000, 200000))
    return text.replace(f'"{_DEEP}"', "[" * depth + "]" * depth, 1).encode()


def yaml_mutation(data: bytes, rng: random.Random) -> bytes:
    import yaml

    special = rng.random()
    if special < 0.06:  # billion laughs
        lines = ['a0: &a0 ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
        lines += [f"a{i}: &a{i} [" + ",".join([f"*a{i - 1}"] * 9) + "]" for i in range(1, 10)]
        return ("\n".join(lines) + "\n").encode() + data
    if special < 0.09:  # a recursive alias
        return b"x: &x [*x]\n" + data
    if special < 0.12:  # a tag that builds Python objects
        tag = f"!!python/object/apply:builtins.exec [\"open('{CODE_MARKER}','w').write('1')\"]"
        return f"pwn: {tag}\n".encode() + data
    if special < 0.15:
        return b"%YAML:1.0\n---\n" + b"- " * 5000 + b"x\n"
    try:
        doc = yaml.safe_load(data.decode("utf-8", "replace").replace("%YAML:1.0", "%YAML 1.1"))
    except yaml.YAMLError:
        return bytes_mutation(data, rng)
    if not isinstance(doc, (dict, list)):
        return bytes_mutation(data, rng)
    doc = _tree_mutation(doc, rng)
    text = yaml.safe_dump(doc, default_flow_style=rng.random() < 0.5, width=10**6)
    depth = rng.choice((100, 1000, 20000))
    return text.replace(_DEEP, "[" * depth + "]" * depth, 1).encode()


# --------------------------------------------------------------------------- NPY / ZIP / PNG


def npy_mutation(data: bytes, rng: random.Random) -> bytes:
    """Rewrite the NPY header: huge or negative shape, hostile dtype, bad header length."""
    if not data.startswith(b"\x93NUMPY") or len(data) < 10:
        return bytes_mutation(data, rng)
    major = data[6]
    hlen_size = 2 if major == 1 else 4
    (hlen,) = struct.unpack("<H" if hlen_size == 2 else "<I", data[8 : 8 + hlen_size])
    start = 8 + hlen_size
    header, body = data[start : start + hlen].decode("latin1"), data[start + hlen :]
    kind = rng.randrange(5)
    if kind == 0:
        shape = rng.choice(
            (
                "(99999999999, 3)",
                "(-1, 3)",
                "(3,)",
                "(2**62, 3)",
                "(0, 3)",
                "(4294967296, 4294967296)",
                "()",
                "(1, 1, 1, 1, 1, 1, 1, 1, 3)",
            )
        )
        header = re.sub(r"'shape': \([^)]*\)", f"'shape': {shape}", header)
    elif kind == 1:
        dtype = rng.choice(
            (
                "'|O'",
                "'<U100'",
                "'|V12'",
                "'>f8'",
                "'<c16'",
                "'|b1'",
                "'<M8[s]'",
                "[('x', '<f8')]",
                "'<f2'",
                "'bogus'",
            )
        )
        header = re.sub(r"'descr': '[^']*'", f"'descr': {dtype}", header)
    elif kind == 2:
        header = header.replace("False", "True")
    elif kind == 3:
        header = rng.choice(("{}", "__import__('os')", "{'descr': '<f8'}", "x" * 70000))
    else:
        return data[:8] + rng.choice((b"\xff\xff", b"\x00\x00", b"\xff\xff\xff\x7f")) + data[10:]
    raw = header.encode("latin1")
    return data[:8] + struct.pack("<H" if hlen_size == 2 else "<I", len(raw) % 65536) + raw + body


def zip_mutation(data: bytes, rng: random.Random) -> bytes:
    """Mutate one member of a ZIP (NPZ, skops), or add a bomb, many members or a path
    outside the folder, or break the declared sizes."""
    try:
        zin = zipfile.ZipFile(io.BytesIO(data))
        members = [(i, zin.read(i)) for i in zin.infolist()]
    except (zipfile.BadZipFile, OSError, ValueError, EOFError, zlib.error):
        return bytes_mutation(data, rng)
    if not members:
        return bytes_mutation(data, rng)
    kind = rng.randrange(6)
    if kind == 5:  # a declared size, CRC or offset of a header becomes hostile
        sig = rng.choice((b"PK\x03\x04", b"PK\x01\x02", b"PK\x05\x06"))
        spots = [m.start() for m in re.finditer(re.escape(sig), data)]
        if spots:
            at = rng.choice(spots) + rng.choice((10, 14, 18, 20, 22, 24, 26, 28, 30, 42, 8, 12))
            return data[:at] + rng.choice(HOSTILE_WORDS[4]).to_bytes(4, "little") + data[at + 4 :]
        return bytes_mutation(data, rng)
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as zout:
        victim = rng.randrange(len(members))
        for k, (info, body) in enumerate(members):
            if k == victim and kind == 0:
                body = npy_mutation(body, rng) if body.startswith(b"\x93NUMPY") else body
                body = json_mutation(body, rng) if info.filename.endswith(".json") else body
                body = bytes_mutation(body, rng) if rng.random() < 0.5 else body
            if k == victim and kind == 1:
                continue  # a missing member
            zout.writestr(info.filename, body)
        if kind == 2:  # a member that inflates to 64 MB
            zout.writestr(members[victim][0].filename + "x", b"\x00" * (64 << 20))
        elif kind == 3:
            for i in range(rng.choice((2000, 20000))):
                zout.writestr(f"m{i}.npy", b"")
        elif kind == 4:
            zout.writestr(rng.choice(("../../escape.npy", "/abs.npy", "a/" * 200 + "b")), b"x")
    return out.getvalue()


def png_mutation(data: bytes, rng: random.Random) -> bytes:
    """A PNG whose IHDR declares a huge or zero size (CRC fixed, so decoders believe it)."""
    if not data.startswith(b"\x89PNG\r\n\x1a\n") or len(data) < 33:
        return bytes_mutation(data, rng)
    w = rng.choice((0, 1, 65535, 100000, 2**31 - 1, 2**32 - 1))
    h = rng.choice((0, 1, 65535, 100000, 2**31 - 1, 2**32 - 1))
    ihdr = bytearray(data[12:29])
    ihdr[4:12] = struct.pack(">II", w, h)
    if rng.random() < 0.3:
        ihdr[12] = rng.choice((0, 3, 16, 255))  # bit depth
    crc = struct.pack(">I", zlib.crc32(bytes(ihdr)) & 0xFFFFFFFF)
    return data[:12] + bytes(ihdr) + crc + data[33:]


_HEADER_LINES = {
    b"ply": [
        b"element vertex 4294967295",
        b"element vertex -1",
        b"element vertex 0",
        b"element face 99999999999",
        b"property list uint int x",
        b"property uchar x",
        b"property double x",
        b"property float128 x",
        b"format binary_big_endian 1.0",
        b"format ascii 1.0",
        b"format binary_little_endian 9.9",
        b"element vertex 3e9",
        b"property float x",
        b"end_header",
    ],
    b"pcd": [
        b"POINTS 4294967295",
        b"WIDTH 99999999999",
        b"HEIGHT 0",
        b"SIZE 8 8",
        b"TYPE U U U",
        b"COUNT 1000000 1 1",
        b"FIELDS x y",
        b"FIELDS rgb",
        b"DATA binary_compressed",
        b"DATA ascii",
        b"SIZE 3 3 3",
        b"TYPE F F F",
        b"COUNT 0 0 0",
        b"VERSION .7",
    ],
}


def header_mutation(data: bytes, rng: random.Random) -> bytes:
    """A PLY or PCD header line is replaced, duplicated or dropped, or a hostile one added."""
    end = data.find(b"end_header\n") if data.startswith(b"ply") else data.find(b"\nDATA ")
    if end < 0:
        return bytes_mutation(data, rng)
    end = data.find(b"\n", end + 1) + 1 or len(data)
    lines = data[:end].split(b"\n")
    pool = _HEADER_LINES[b"ply" if data.startswith(b"ply") else b"pcd"]
    i = rng.randrange(1, max(2, len(lines) - 1))
    kind = rng.randrange(4)
    if kind == 0:
        lines[i] = rng.choice(pool)
    elif kind == 1:
        lines.insert(i, rng.choice(pool))
    elif kind == 2:
        del lines[i]
    else:
        lines[i : i + 1] = [lines[i]] * rng.choice((2, 50, 5000))
    return b"\n".join(lines) + data[end:]


#: LAS header fields (offset, width): header size, offset to points, VLR count, point
#: format, record length, legacy point count, LAS 1.4 point count, EVLR start and count.
_LAS_FIELDS = [
    (94, 2),
    (96, 4),
    (100, 4),
    (104, 1),
    (105, 2),
    (107, 4),
    (247, 8),
    (235, 8),
    (243, 4),
    (24, 1),
    (25, 1),
    (131, 8),
    (155, 8),
]


def las_mutation(data: bytes, rng: random.Random) -> bytes:
    """A count, offset, size or version field of a LAS/LAZ header becomes hostile."""
    if not data.startswith(b"LASF") or len(data) < 375:
        return bytes_mutation(data, rng)
    at, width = rng.choice(_LAS_FIELDS)
    value = rng.choice(HOSTILE_WORDS[width] + [1, 2, 3, 10, 200])
    raw = (value % (1 << (8 * width))).to_bytes(width, "little")
    return data[:at] + raw + data[at + width :]


STRUCTURED: dict[str, Mutator] = {
    "header": header_mutation,
    "las": las_mutation,
    "json": json_mutation,
    "yaml": yaml_mutation,
    "npy": npy_mutation,
    "zip": zip_mutation,
    "png": png_mutation,
    "text": text_line,
}


def mutate_file(data: bytes, kind: str, rng: random.Random, others: list[bytes]) -> bytes:
    """One mutation of a file of ``kind`` (a key of :data:`STRUCTURED` or "bytes"): half
    structure-aware when the kind has a mutator, a few percent another format's bytes."""
    roll = rng.random()
    if roll < 0.04 and others:
        return rng.choice(others)  # the wrong type of file
    if kind in STRUCTURED and roll < 0.55:
        return STRUCTURED[kind](data, rng)
    return bytes_mutation(data, rng)


# --------------------------------------------------------------------------- hostile values


def hostile_array(rng: random.Random, like: Any = None) -> Any:
    """An array argument a caller should not pass: NaN, inf, empty, wrong shape or dtype,
    huge values, ragged lists, objects, strings; or a slightly damaged copy of ``like``."""
    import numpy as np

    if like is not None and rng.random() < 0.5:
        a = np.array(like, dtype=float, copy=True)
        flat = a.reshape(-1)
        if flat.size:
            idx = rng.sample(range(flat.size), min(flat.size, rng.choice((1, 10, flat.size))))
            flat[idx] = rng.choice((np.nan, np.inf, -np.inf, 1e308, -1e308, 0.0, 1e-320))
        return a
    choices: list[Callable[[], Any]] = [
        lambda: np.empty((0, 3)),
        lambda: np.zeros((rng.choice((1, 2, 3, 7)), 3)),
        lambda: np.full((100, 3), np.nan),
        lambda: np.full((100, 3), np.inf),
        lambda: np.full((50, 50), 1e308),
        lambda: np.ones((5, 2)),
        lambda: np.ones((5, 3, 1)),
        lambda: np.ones(7),
        lambda: np.float64(3.0),
        lambda: np.array(["a", "b", "c"]),
        lambda: np.array([object(), None, 1], dtype=object),
        lambda: [[1, 2, 3], [1, 2]],
        lambda: np.ones((100, 3), dtype=np.complex128),
        lambda: np.ones((100, 3), dtype=bool),
        lambda: np.arange(300, dtype=np.int8).reshape(100, 3),
        lambda: np.zeros((0, 0)),
        lambda: np.ones((64, 0)),
        lambda: np.random.default_rng(rng.getrandbits(32)).normal(0, 1e6, (200, 3)),
        lambda: None,
        lambda: "points.npy",
    ]
    return rng.choice(choices)()


def hostile_scalar(rng: random.Random, typical: float) -> Any:
    return rng.choice(
        (
            typical,
            0,
            -typical,
            math.nan,
            math.inf,
            -math.inf,
            1e-300,
            1e300,
            2**64,
            -(2**63),
            "0.1",
            None,
            True,
            [typical],
            typical * 1e6,
        )
    )


def hostile_int(rng: random.Random, typical: int) -> Any:
    return rng.choice((typical, 0, -1, 1, 2**31, 2**63, 10**30, 2.5, math.nan, None, "8"))
