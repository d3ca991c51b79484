"""The crashes that rough_map's own checks stand in front of, shown on the installed libraries.

rough_map reads its inputs with the libraries and turns their errors into one-line errors
(:class:`~rough_map.errors.FileFormatError`, :class:`~rough_map.errors.ModelError`). Some
inputs crash a library outright: a signal, not an exception anyone could catch, or memory
taken without bound until the kernel's OOM killer ends the process. There a check of
rough_map's own runs before the library sees the input. Each test here runs the library
alone, in a child process, on such an input and asserts that the process dies of it (or
takes the memory). Then it shows rough_map reading or refusing the same input in one line.

When a library upgrade stops a crash, its test fails, and the check it names may go (SECURITY.md
lists them).
"""

from __future__ import annotations

import signal
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from bag_cases import write_compressed

from rough_map.errors import FileFormatError
from rough_map.io.pointcloud import read_cloud
from rough_map.io.rosbag import inspect_bag

CRASHES = {-signal.SIGSEGV: "SIGSEGV", -signal.SIGABRT: "SIGABRT", -signal.SIGBUS: "SIGBUS"}


def _library_alone(code: str, *args: str) -> subprocess.CompletedProcess[str]:
    """``code`` run by a fresh interpreter with ``args``: the library without rough_map."""
    return subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=300
    )


def _assert_crashes(proc: subprocess.CompletedProcess[str], what: str) -> None:
    assert proc.returncode in CRASHES, (
        f"{what} no longer crashes on this input (exit {proc.returncode}, "
        f"{proc.stderr.strip()[-300:]!r}): the check in front of it may go"
    )


def test_open3d_pcd_reader_segfaults_on_a_lone_normal_field(tmp_path: Path) -> None:
    """A well-formed PCD whose fields are x, y, z and normal_x alone: open3d's reader dies on
    it (SIGSEGV, open3d 0.20). rough_map reads PCD and PLY with its own numpy reader
    (:mod:`rough_map.io.ply_pcd`), which takes x, y, z and skips the other fields."""
    xyz = np.random.default_rng(0).normal(size=(100, 4)).astype("<f4")
    header = (
        "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z normal_x\nSIZE 4 4 4 4\nTYPE F F F F\n"
        "COUNT 1 1 1 1\nWIDTH 100\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 100\nDATA binary\n"
    )
    path = tmp_path / "lone_normal.pcd"
    path.write_bytes(header.encode() + xyz.tobytes())
    code = "import open3d, sys; open3d.io.read_point_cloud(sys.argv[1])"
    _assert_crashes(_library_alone(code, str(path)), "open3d.io.read_point_cloud")
    np.testing.assert_array_equal(read_cloud(path), xyz[:, :3].astype(float))


def test_open3d_ply_reader_makes_up_points_past_the_end_of_a_file(tmp_path: Path) -> None:
    """Not a crash, but why PLY is read by the same numpy reader: a binary PLY that declares
    100,000 vertices and holds 100 gives open3d's reader 100,000 points, the missing ones
    made up, with only a warning on stderr (open3d 0.20). rough_map refuses the file."""
    xyz = np.random.default_rng(0).normal(size=(100, 3)).astype("<f4")
    header = "ply\nformat binary_little_endian 1.0\nelement vertex 100000\n"
    header += "property float x\nproperty float y\nproperty float z\nend_header\n"
    path = tmp_path / "short.ply"
    path.write_bytes(header.encode() + xyz.tobytes())
    code = "import open3d, sys; print(len(open3d.io.read_point_cloud(sys.argv[1]).points))"
    proc = _library_alone(code, str(path))
    assert proc.returncode == 0 and proc.stdout.split()[-1] == "100000", proc.stdout
    with pytest.raises(FileFormatError, match=r"short\.ply \[points\]: truncated"):
        read_cloud(path)


def test_lazrs_aborts_on_an_absurd_chunk_count(tmp_path: Path) -> None:
    """A LAZ whose chunk table declares 2^31 - 1 chunks: lazrs allocates the table before it
    reads it and aborts the process (SIGABRT, lazrs 0.8). rough_map checks the chunk table
    against the point count and the file first (:func:`rough_map.io.las.check_las_header`)."""
    from rough_map.io.las import write_las

    path = tmp_path / "chunks.laz"
    write_las(path, np.random.default_rng(1).normal(size=(500, 3)))
    data = bytearray(path.read_bytes())
    offset = struct.unpack_from("<I", data, 96)[0]  # offset to the point data
    table = struct.unpack_from("<q", data, offset)[0]  # where the chunk table starts
    struct.pack_into("<I", data, table + 4, 2**31 - 1)  # its number of chunks
    path.write_bytes(bytes(data))
    code = "import laspy, sys; laspy.read(sys.argv[1])"
    _assert_crashes(_library_alone(code, str(path)), "laspy.read with lazrs")
    with pytest.raises(FileFormatError, match=r"chunks\.laz \[chunk_table\]: 2147483647 chunks"):
        read_cloud(path)


def test_lazrs_aborts_on_a_forged_layer_size(tmp_path: Path) -> None:
    """A layered (LAS 1.4) LAZ file of under 1 kB whose first chunk declares a layer of 4 GiB:
    lazrs (0.8) allocates the layer before reading it, so it takes 4 GiB and 13 s, or aborts
    the process (SIGABRT) when the memory is not there, as under a 1 GiB cap here. rough_map
    walks the chunks' layer sizes first (``_check_laz_layers`` in
    :func:`rough_map.io.las.check_las_header`)."""
    from rough_map.io.las import write_las

    path = tmp_path / "layer.laz"
    write_las(path, np.random.default_rng(1).normal(size=(46, 3)))
    data = bytearray(path.read_bytes())
    offset = struct.unpack_from("<I", data, 96)[0]  # offset to the point data
    # after the chunk table's offset, the first point (raw), the chunk's point count: the
    # byte sizes of its layers; the sixth is forged
    struct.pack_into("<I", data, offset + 8 + 30 + 4 + 20, 2**32 - 16)
    path.write_bytes(bytes(data))
    assert path.stat().st_size < 1024
    code = (
        "import resource, sys; resource.setrlimit(resource.RLIMIT_AS, (2**30, 2**30)); "
        "import laspy; laspy.read(sys.argv[1])"
    )
    _assert_crashes(_library_alone(code, str(path)), "laspy.read with lazrs under 1 GiB")
    with pytest.raises(FileFormatError, match=r"layer\.laz \[points\]: LAZ chunk 0 declares"):
        read_cloud(path)


def test_laspy_hangs_on_an_absurd_vlr_count(tmp_path: Path) -> None:
    """A LAS header declaring 2^32 - 1 VLRs: laspy (2.7) reads VLR after VLR past the end of
    the file and does not return (still running after 120 s; stopped here after 10).
    rough_map checks the VLRs against the bytes before the points first (``_check_vlrs`` in
    :func:`rough_map.io.las.check_las_header`)."""
    from rough_map.io.las import write_las

    path = tmp_path / "vlrs.las"
    write_las(path, np.random.default_rng(1).normal(size=(46, 3)))
    data = bytearray(path.read_bytes())
    struct.pack_into("<I", data, 100, 2**32 - 1)  # number of VLRs
    path.write_bytes(bytes(data))
    with pytest.raises(subprocess.TimeoutExpired):
        subprocess.run(
            [sys.executable, "-c", "import laspy, sys; laspy.read(sys.argv[1])", str(path)],
            capture_output=True,
            timeout=10,
        )
    with pytest.raises(FileFormatError, match=r"vlrs\.las \[vlrs\]: 4294967295 VLRs cannot"):
        read_cloud(path)


def test_sklearn_tree_segfaults_on_a_child_index_out_of_range(tmp_path: Path) -> None:
    """A forest whose tree points a node at a child beyond its nodes, rebuilt by skops as any
    model file is: scikit-learn's compiled tree walk reads the node without a bounds check and
    dies (SIGSEGV, scikit-learn 1.9). rough_map checks every tree's node indices after skops
    has rebuilt a model and before anything predicts with it
    (:mod:`rough_map.classify._checks`; ``tests/test_fuzz_models.py`` shows the one-line
    ModelError)."""
    code = """
import sys
import numpy as np
import skops.io as sio
from sklearn.ensemble import RandomForestClassifier
X = np.random.default_rng(0).normal(size=(200, 4))
forest = RandomForestClassifier(n_estimators=2, random_state=0).fit(X, X[:, 0] > 0)
forest.estimators_[0].tree_.children_left[0] = 2**40
sio.dump(forest, sys.argv[1])
loaded = sio.load(sys.argv[1], trusted=sio.get_untrusted_types(file=sys.argv[1]))
print("loaded", flush=True)
loaded.predict(X[:5])
"""
    proc = _library_alone(code, str(tmp_path / "forest.skops"))
    assert "loaded" in proc.stdout  # skops rebuilt the tree as the file gave it
    _assert_crashes(proc, "RandomForestClassifier.predict")


def _lz4_chunk_bomb(bag: Path, out: Path, extra: int) -> None:
    """``bag`` (ROS 1, one lz4 chunk) with ``extra`` zero bytes after the chunk's records,
    its declared size and the bag's index position made to match: a valid bag that is 250
    times smaller than what its chunk expands to."""
    import lz4.frame

    data = bytearray(bag.read_bytes())
    records, pos = [], 13  # after "#ROSBAG V2.0\n": header length, header, data length, data
    while pos < len(data):
        hlen = struct.unpack_from("<I", data, pos)[0]
        header, fields, i = data[pos + 4 : pos + 4 + hlen], {}, 0
        while i < hlen:
            n = struct.unpack_from("<I", header, i)[0]
            name, value = bytes(header[i + 4 : i + 4 + n]).split(b"=", 1)
            fields[name] = (pos + 4 + i + 4 + len(name) + 1, value)
            i += 4 + n
        dlen = struct.unpack_from("<I", data, pos + 4 + hlen)[0]
        records.append((pos, hlen, dlen, fields))
        pos += 8 + hlen + dlen
    (chunk,) = [r for r in records if r[3][b"op"][1] == b"\x05"]
    (head,) = [r for r in records if r[3][b"op"][1] == b"\x03"]
    pos, hlen, dlen, fields = chunk
    start = pos + 8 + hlen
    raw = lz4.frame.decompress(bytes(data[start : start + dlen]))
    packed = lz4.frame.compress(raw + bytes(extra))
    struct.pack_into("<I", data, fields[b"size"][0], len(raw) + extra)
    struct.pack_into("<I", data, start - 4, len(packed))
    index_at = head[3][b"index_pos"][0]
    index = struct.unpack_from("<Q", data, index_at)[0]
    struct.pack_into("<Q", data, index_at, index + len(packed) - dlen)
    out.write_bytes(bytes(data[:start] + packed + data[start + dlen :]))


def test_rosbags_expands_a_chunk_bomb_in_memory(tmp_path: Path) -> None:
    """A ROS 1 bag whose lz4 chunk expands 250 times: rosbags decompresses each chunk whole
    into memory (rosbags 0.11), so a bag of a few MB takes GB and one of a
    hundred MB takes more memory than the machine has. rough_map walks the bag's records
    first (:mod:`rough_map.io.rosbag.checks`) and refuses a chunk that declares more than
    ``LIMITS.bag_chunk`` or decompresses to another size than it declares, decompressing in
    steps of 1 MiB that it drops."""
    bag = write_compressed(tmp_path / "drive", "lz4")
    bomb = tmp_path / "bomb.bag"
    _lz4_chunk_bomb(bag, bomb, 300 << 20)
    code = """
import re, sys
from pathlib import Path
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
with AnyReader([Path(sys.argv[1])], default_typestore=get_typestore(Stores.ROS1_NOETIC)) as r:
    n = sum(1 for _ in r.messages())
peak = re.search(r"VmHWM:\\s+(\\d+) kB", Path("/proc/self/status").read_text())[1]
print(n, int(peak) // 1024)  # messages, peak resident MiB of this process
"""
    plain, expanded = (_library_alone(code, str(p)).stdout.split() for p in (bag, bomb))
    assert plain[0] == expanded[0]  # the same messages: the bag is valid
    peak = int(expanded[1]) - int(plain[1])
    assert bomb.stat().st_size < 2 << 20
    assert peak > 300, f"rosbags took {peak} MiB more for the bomb: it no longer expands it whole"
    with pytest.raises(
        FileFormatError, match=r"bomb\.bag \[ros1 chunk\]: .*chunk declares 314577695 B"
    ):
        inspect_bag(bomb)


def test_numpy_expands_an_archive_member_whole_in_memory(tmp_path: Path) -> None:
    """An ``.npz`` of 0.3 MB whose member is 300 MiB of zeros, declared honestly:
    ``np.load`` inflates it whole (numpy 2), so an archive of a hundred MB can take more
    memory than the machine has. rough_map's reader (:mod:`rough_map.io.safe_npz`) refuses
    arrays of more than ``LIMITS.archive_ratio`` times the archive before inflating them,
    and inflates members in 1 MiB pieces."""
    path = tmp_path / "bomb.npz"
    np.savez_compressed(path, points=np.zeros(((300 << 20) // 24, 3)))
    code = """
import re, sys
from pathlib import Path
import numpy as np
with np.load(sys.argv[1]) as archive:
    shape = archive["points"].shape
peak = re.search(r"VmHWM:\\s+(\\d+) kB", Path("/proc/self/status").read_text())[1]
print(shape[0], int(peak) // 1024)  # points, peak resident MiB of this process
"""
    proc = _library_alone(code, str(path))
    points, peak = (int(v) for v in proc.stdout.split())
    assert points == (300 << 20) // 24 and path.stat().st_size < 1 << 20
    assert peak > 300, f"np.load took {peak} MiB: it no longer inflates a member whole"
    with pytest.raises(FileFormatError, match=r"bomb\.npz \[points\]: declares 314572"):
        read_cloud(path)
