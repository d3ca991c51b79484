"""Fuzzing of the point-cloud and image readers: every mutated file gives points or a one-line
FileFormatError, never another exception, a crash, or an allocation its size does not justify.

Bases are small valid files of each format; regression tests below pin inputs that once broke a
reader (open3d crashes on corrupt PLY/PCD, forged .npy shapes, LAS counts that made the LAZ
decoder abort, PNG decompression bombs).
"""

from __future__ import annotations

import io
import re
import struct
import zipfile
import zlib
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest
from fuzzing import FUZZ, SEEDS, assert_bounded, mutate, write_case
from hypothesis import given

from rough_map.errors import FileFormatError
from rough_map.io.images import read_image
from rough_map.io.ply_pcd import lzf_decompress
from rough_map.io.pointcloud import read_cloud, read_kitti_poses, write_cloud
from rough_map.simulate.course import save_cloud_npz

pytestmark = pytest.mark.fuzz

POINTS = np.random.default_rng(14).normal(size=(40, 3)) * [2.0, 1.0, 0.05]


def _written(suffix: str, tmp: Path, write=None) -> bytes:
    path = tmp / f"base{suffix}"
    (write or write_cloud)(path, POINTS)
    return path.read_bytes()


def _open3d_legacy(path: Path, points: np.ndarray, **kwargs: bool) -> None:
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    assert o3d.io.write_point_cloud(str(path), cloud, **kwargs)


def _npy(array: np.ndarray) -> bytes:
    out = io.BytesIO()
    np.save(out, array, allow_pickle=False)
    return out.getvalue()


def _npz(compress: bool = True, **arrays: np.ndarray) -> bytes:
    out = io.BytesIO()
    (np.savez_compressed if compress else np.savez)(out, **arrays)
    return out.getvalue()


def ply_ascii_with_faces() -> bytes:
    """An ASCII PLY with extra vertex properties, a face element and comments."""
    rows = "".join(f"{x:.17g} {y:.17g} {z:.17g} 255 0 0 0.5\n" for x, y, z in POINTS[:4])
    return (
        "ply\nformat ascii 1.0\ncomment made by hand\nelement vertex 4\n"
        "property float64 x\nproperty double y\nproperty double z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nproperty float s\n"
        "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
        f"{rows}3 0 1 2\n3 1 2 3\n"
    ).encode()


def ply_big_endian() -> bytes:
    """A big-endian binary PLY: int16 id, float32 x, y, z, then a face element."""
    dtype = np.dtype([("id", ">i2"), ("x", ">f4"), ("y", ">f4"), ("z", ">f4")])
    rows = np.zeros(len(POINTS), dtype)
    rows["id"] = np.arange(len(POINTS))
    for k, c in enumerate("xyz"):
        rows[c] = POINTS[:, k]
    header = (
        f"ply\nformat binary_big_endian 1.0\nelement vertex {len(POINTS)}\n"
        "property short id\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
    ).encode()
    return header + rows.tobytes() + b"\x03" + np.array([0, 1, 2], ">i4").tobytes()


def _bases(tmp: Path) -> dict[str, bytes]:
    legacy = {}
    for name, kwargs in (
        ("ascii.ply", {"write_ascii": True}),
        ("ascii.pcd", {"write_ascii": True}),
        ("compressed.pcd", {"compressed": True}),
    ):
        _open3d_legacy(tmp / name, POINTS, **kwargs)
        legacy[name] = (tmp / name).read_bytes()
    columns = {c: POINTS[:, k].astype(np.float32) for k, c in enumerate("xyz")}
    save_cloud_npz(tmp / "c.npz", POINTS)
    image = (np.add.outer(np.arange(24), np.arange(32)) * 4).astype(np.uint8)
    return {
        "c.npy": _npy(POINTS),
        "points.npz": _npz(points=POINTS),
        "columns.npz": _npz(False, **columns),
        "scaled.npz": (tmp / "c.npz").read_bytes(),
        "c.csv": _written(".csv", tmp),
        "c.xyz": b"".join(b"%.6f %.6f %.6f\n" % tuple(p) for p in POINTS),
        "binary.ply": _written(".ply", tmp),
        "faces.ply": ply_ascii_with_faces(),
        "big.ply": ply_big_endian(),
        "binary.pcd": _written(".pcd", tmp),
        **legacy,
        "c.las": _written(".las", tmp),
        "c.laz": _written(".laz", tmp),
        "c.bin": np.column_stack([POINTS, np.ones(len(POINTS))]).astype("<f4").tobytes(),
        "poses.txt": b"".join(
            b" ".join(b"%.6e" % v for v in np.eye(3, 4).ravel() + k) + b"\n" for k in range(5)
        ),
        "i.png": cv2.imencode(".png", image)[1].tobytes(),
        "i.jpg": cv2.imencode(".jpg", cv2.cvtColor(image, cv2.COLOR_GRAY2BGR))[1].tobytes(),
    }


@pytest.fixture(scope="module")
def bases(tmp_path_factory: pytest.TempPathFactory) -> dict[str, bytes]:
    return _bases(tmp_path_factory.mktemp("bases"))


def _limit(data: bytes) -> int:
    """Allocation allowed for reading a file of this size: a small multiple, plus slack."""
    return 64 * len(data) + 32 * 2**20


def fuzz_read(factory: pytest.TempPathFactory, name: str, base: bytes, seed: int) -> object:
    data = mutate(base, seed)
    path = write_case(factory, name, data)
    if name.endswith((".png", ".jpg")):
        return assert_bounded(read_image, path, max_bytes=_limit(data))
    reader = read_kitti_poses if name == "poses.txt" else read_cloud
    return assert_bounded(reader, path, max_bytes=_limit(data))


# --------------------------------------------------------------------------------------------
# Fuzz targets: one per format


def _target(name: str):
    @FUZZ
    @given(seed=SEEDS)
    def test(bases: dict[str, bytes], tmp_path_factory: pytest.TempPathFactory, seed: int):
        fuzz_read(tmp_path_factory, name, bases[name], seed)

    test.__name__ = f"test_fuzz_{name.replace('.', '_')}"
    return test


test_fuzz_npy = _target("c.npy")
test_fuzz_npz_points = _target("points.npz")
test_fuzz_npz_columns = _target("columns.npz")
test_fuzz_npz_scaled = _target("scaled.npz")
test_fuzz_csv = _target("c.csv")
test_fuzz_xyz = _target("c.xyz")
test_fuzz_ply_binary = _target("binary.ply")
test_fuzz_ply_ascii = _target("ascii.ply")
test_fuzz_ply_faces = _target("faces.ply")
test_fuzz_ply_big_endian = _target("big.ply")
test_fuzz_pcd_binary = _target("binary.pcd")
test_fuzz_pcd_ascii = _target("ascii.pcd")
test_fuzz_pcd_compressed = _target("compressed.pcd")
test_fuzz_las = _target("c.las")
test_fuzz_laz = _target("c.laz")
test_fuzz_kitti_bin = _target("c.bin")
test_fuzz_kitti_poses = _target("poses.txt")
test_fuzz_png = _target("i.png")
test_fuzz_jpg = _target("i.jpg")


def test_bases_read(bases: dict[str, bytes], tmp_path: Path) -> None:
    """The unmutated bases read back to the points they were written from."""
    for name, data in bases.items():
        (tmp_path / name).write_bytes(data)
        if name.endswith((".png", ".jpg")):
            assert read_image(tmp_path / name).shape == (24, 32)
            continue
        if name == "poses.txt":
            assert read_kitti_poses(tmp_path / name).shape == (5, 4, 4)
            continue
        got = read_cloud(tmp_path / name)
        want = POINTS[:4] if name == "faces.ply" else POINTS
        if name == "scaled.npz":  # save_cloud_npz sorts the points by x
            want = want[np.argsort(want[:, 0], kind="stable")]
        atol = {"c.las": 1e-4, "c.laz": 1e-4, "scaled.npz": 1e-3}.get(name, 2e-5)
        np.testing.assert_allclose(got, want, atol=atol, rtol=1e-6, err_msg=name)


# --------------------------------------------------------------------------------------------
# Regression tests: inputs that broke a reader, and crafted headers


def bounded(fn, *args, max_bytes: int | None = None):
    """:func:`assert_bounded`, raising the one-line error it returns (for pytest.raises)."""
    result = assert_bounded(fn, *args, max_bytes=max_bytes)
    if isinstance(result, FileFormatError):
        raise result
    return result


def test_ply_and_pcd_declaring_huge_counts(bases: dict[str, bytes], tmp_path: Path) -> None:
    for name, old, new in (
        ("binary.ply", b"element vertex 40", b"element vertex 1999999999"),
        ("ascii.ply", b"element vertex 40", b"element vertex 1999999999"),
        ("binary.pcd", b"POINTS 40", b"POINTS 1999999999"),
        ("ascii.pcd", b"POINTS 40", b"POINTS 1999999999"),
    ):
        path = tmp_path / name
        path.write_bytes(bases[name].replace(old, new))
        with pytest.raises(FileFormatError, match=rf"{name} \[points\]: truncated: the file"):
            bounded(read_cloud, path, max_bytes=2**20)
    (tmp_path / "over.pcd").write_bytes(
        bases["binary.pcd"].replace(b"POINTS 40", b"POINTS 9999999999")
    )
    (tmp_path / "over.ply").write_bytes(
        bases["binary.ply"].replace(b"vertex 40", b"vertex 9999999999")
    )
    with pytest.raises(FileFormatError, match=r"over\.ply \[count\]: .* 9999999999 'vertex'"):
        read_cloud(tmp_path / "over.ply")
    with pytest.raises(FileFormatError, match=r"over\.pcd \[POINTS\]: .* 9999999999 points"):
        read_cloud(tmp_path / "over.pcd")


def test_truncated_binary_bodies(bases: dict[str, bytes], tmp_path: Path) -> None:
    for name in ("binary.ply", "big.ply", "binary.pcd", "compressed.pcd"):
        data = bases[name]
        path = tmp_path / name
        path.write_bytes(data[: len(data) - 200])
        with pytest.raises(FileFormatError, match=rf"{name} \[points\]: truncated"):
            read_cloud(path)


def test_corrupt_ply_and_pcd_headers(bases: dict[str, bytes], tmp_path: Path) -> None:
    cases = {
        "nox.ply": (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float y\n"
                    b"property float z\nend_header\n1 2\n", r"\[x\]: the vertex element has no"),
        "list.ply": (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty "
                     b"float y\nproperty float z\nproperty list uchar int i\nend_header\n1 2 3 0\n",
                     r"\[vertex\]: list properties in the vertex element are not supported"),
        "face1st.ply": (b"ply\nformat binary_little_endian 1.0\nelement face 1\nproperty list "
                        b"uchar int i\nelement vertex 1\nproperty float x\nproperty float y\n"
                        b"property float z\nend_header\n" + bytes(30),
                        r"\[vertex\]: element 'face' with list properties before the vertices"),
        "fmt.ply": (b"ply\nformat binary_middle_endian 1.0\nend_header\n",
                    r"\[header\]: header line not understood: 'format binary_middle"),
        "count.ply": (b"ply\nformat ascii 1.0\nelement vertex -5\nend_header\n",
                      r"\[element 'vertex'\]: element count '-5' is not a count"),
        "utf.ply": (b"ply\nformat ascii 1.0\ncomment \xff\nend_header\n",
                    r"\[header\]: the header is not ASCII text \(byte 29\)"),
        "type.pcd": (b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F Q\nCOUNT 1 1 1\nPOINTS 1\nDATA ascii\n",
                     r"\[TYPE\]: unsupported TYPE 'Q' with SIZE 4"),
        "nz.pcd": (b"FIELDS x y\nSIZE 4 4\nTYPE F F\nPOINTS 1\nDATA binary\n" + bytes(8),
                   r"\[z\]: no field 'z' in FIELDS"),
        "size.pcd": (b"FIELDS x y z\nSIZE 4 4\nTYPE F F F\nPOINTS 1\nDATA binary\n" + bytes(12),
                     r"\[SIZE\]: 2 values for 3 FIELDS"),
        "kind.pcd": (b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 1\nDATA binary_lzma\n",
                     r"\[DATA\]: unknown DATA kind 'binary_lzma'"),
        "words.pcd": (b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 2\nDATA ascii\n"
                      b"1 2 3\n4 five 6\n", r"\[points\]: not a table of numbers: could not"),
    }  # fmt: skip
    for name, (data, match) in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(FileFormatError, match=re.escape(name) + " " + match):
            bounded(read_cloud, tmp_path / name)


def test_pcd_compressed_forged_sizes(bases: dict[str, bytes], tmp_path: Path) -> None:
    data = bases["compressed.pcd"]
    at = data.index(b"DATA binary_compressed\n") + len(b"DATA binary_compressed\n")
    compressed, size = struct.unpack_from("<II", data, at)
    forged = {
        "big.pcd": (struct.pack("<II", 2**32 - 1, size), r"\[points\]: truncated"),
        "odd.pcd": (struct.pack("<II", compressed, size + 4), r"\[POINTS\]: compressed data of"),
    }
    for name, (sizes, match) in forged.items():
        (tmp_path / name).write_bytes(data[:at] + sizes + data[at + 8 :])
        with pytest.raises(FileFormatError, match=re.escape(name) + " " + match):
            read_cloud(tmp_path / name)
    # Flipped bytes in the LZF stream: a back reference out of range, or the wrong length.
    body = bytearray(data)
    body[at + 8] = 0xFF
    (tmp_path / "lzf.pcd").write_bytes(bytes(body))
    with pytest.raises(FileFormatError, match=r"lzf\.pcd \[DATA\]: corrupt compressed data"):
        read_cloud(tmp_path / "lzf.pcd")


def test_lzf_decompress() -> None:
    # literal "abc", then a back reference of length 7 at distance 3 (overlapping)
    assert lzf_decompress(b"\x02abc" + bytes([(5 << 5) | 0, 2]), 10) == b"abcabcabca"
    with pytest.raises(ValueError, match="back reference out of range"):
        lzf_decompress(bytes([(1 << 5), 9]), 3)
    with pytest.raises(ValueError, match="inflated to 3 B instead of 4 B"):
        lzf_decompress(b"\x02abc", 4)
    with pytest.raises(ValueError, match="literal run past the end"):
        lzf_decompress(b"\x05ab", 100)


def _npy_header(text: bytes) -> bytes:
    text += b" " * (-(len(text) + 11) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text


def test_npy_forged_headers(tmp_path: Path) -> None:
    cases = {
        # numpy's fallback for old headers tokenizes this and raised tokenize.TokenError
        "token.npy": (_npy_header(b"{'descr': '<f8', 'fortran_order': False, 'shape': ((("),
                      r"token\.npy: not a readable \.npy file \(truncated\?\): bad header"),
        "huge.npy": (_npy_header(b"{'descr': '<f8', 'fortran_order': False, "
                                 b"'shape': (1000000000000, 3), }") + bytes(48),
                     r"huge\.npy: shape \(1000000000000, 3\) does not fit \(truncated\?\): 8 B "
                     r"items need 24000000000000 B, the data holds 48 B"),
        "magic.npy": (b"\x93NUMPY\x07\x00" + bytes(100), r"magic\.npy: .*bad header"),
        "zip.npy": (b"PK\x03\x04" + bytes(30), r"zip\.npy: this is an \.npz archive"),
    }  # fmt: skip
    for name, (data, match) in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(FileFormatError, match=match):
            bounded(read_cloud, tmp_path / name, max_bytes=2**20)


def test_npz_forged_members(bases: dict[str, bytes], tmp_path: Path) -> None:
    data = bases["points.npz"]
    central = data.index(b"PK\x01\x02")
    forged = bytearray(data)
    forged[central + 24 : central + 28] = struct.pack("<I", 2**32 - 2)  # uncompressed size
    (tmp_path / "bomb.npz").write_bytes(bytes(forged))
    with pytest.raises(FileFormatError, match=r"bomb\.npz \[points\]: declares 4294967294 bytes"):
        bounded(read_cloud, tmp_path / "bomb.npz", max_bytes=2**20)
    # A real deflate bomb: 50 MB of zeros in a tiny member, declared honestly.
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as zf:
        with zf.open("points.npy", "w", force_zip64=True) as member:
            member.write(_npy_header(b"{'descr': '<f8', 'fortran_order': False, 'shape': "
                                     b"(2083333, 3), }"))  # fmt: skip
            for _ in range(50):
                member.write(bytes(10**6))
    (tmp_path / "zeros.npz").write_bytes(out.getvalue())
    with pytest.raises(FileFormatError, match=r"zeros\.npz \[points\]: declares"):
        bounded(read_cloud, tmp_path / "zeros.npz", max_bytes=2**20)
    # Flipped bytes in the compressed stream of a member.
    body = bytearray(data)
    start = data.index(b"points.npy") + len(b"points.npy")
    body[start + 20 : start + 40] = bytes(20)
    (tmp_path / "flip.npz").write_bytes(bytes(body))
    with pytest.raises(FileFormatError, match=r"flip\.npz \[points\]: (damaged|.*bad header)"):
        read_cloud(tmp_path / "flip.npz")
    (tmp_path / "zlib.npz").write_bytes(zlib.compress(b"not a zip"))
    with pytest.raises(FileFormatError, match=r"zlib\.npz: not a readable \.npz archive"):
        read_cloud(tmp_path / "zlib.npz")


def _patched(data: bytes, at: int, fmt: str, value: int) -> bytes:
    out = bytearray(data)
    struct.pack_into(fmt, out, at, value)
    return bytes(out)


def test_las_declaring_huge_counts(bases: dict[str, bytes], tmp_path: Path, monkeypatch) -> None:
    import lazrs

    las, laz = bases["c.las"], bases["c.laz"]
    (tmp_path / "huge.las").write_bytes(_patched(las, 247, "<Q", 2**62))
    with pytest.raises(FileFormatError, match=r"huge\.las \[points\]: truncated: 40 of the 46"):
        bounded(read_cloud, tmp_path / "huge.las", max_bytes=2**20)

    def boom(*args, **kwargs):  # the LAZ decoder must not see these files
        raise AssertionError("lazrs called")

    for name in ("LasZipDecompressor", "ParLasZipDecompressor"):
        monkeypatch.setattr(lazrs, name, boom)
    for count in (2**62, 2**32 - 1, 10**6):
        (tmp_path / "huge.laz").write_bytes(_patched(laz, 247, "<Q", count))
        with pytest.raises(
            FileFormatError,
            match=rf"huge\.laz \[points\]: the header declares "
            rf"{count} points of 30 B in \d+ B of LAZ data",
        ):
            bounded(read_cloud, tmp_path / "huge.laz", max_bytes=2**20)
    (tmp_path / "vlrs.las").write_bytes(_patched(las, 100, "<I", 2**32 - 1))
    with pytest.raises(FileFormatError, match=r"vlrs\.las \[vlrs\]: 4294967295 VLRs cannot fit"):
        read_cloud(tmp_path / "vlrs.las")
    (tmp_path / "evlrs.las").write_bytes(_patched(las, 243, "<I", 2**32 - 1))
    with pytest.raises(FileFormatError, match=r"evlrs\.las \[evlrs\]: 4294967295 EVLRs"):
        read_cloud(tmp_path / "evlrs.las")
    (tmp_path / "offset.las").write_bytes(_patched(las, 96, "<I", 2**32 - 1))
    with pytest.raises(FileFormatError, match=r"offset\.las \[header\]: header size 375 B and"):
        read_cloud(tmp_path / "offset.las")


def test_laz_forged_chunks(bases: dict[str, bytes], tmp_path: Path) -> None:
    """A layer size of 4 GB in a chunk made the decoder allocate (and zero) it: seconds, or an
    abort when several layers did so. The decoder reads chunks in order whatever the chunk
    table says, so a table moved elsewhere does not hide the forged chunk."""
    laz = bases["c.laz"]
    offset = struct.unpack_from("<I", laz, 96)[0]
    first_layer = offset + 8 + 30 + 4  # chunk table offset, raw first point, point count
    forged = _patched(laz, first_layer + 20, "<I", 2**32 - 16)
    for name, data in (("layer.laz", forged), ("table.laz", _patched(forged, offset, "<q", 836))):
        (tmp_path / name).write_bytes(data)
        with pytest.raises(
            FileFormatError, match=rf"{name} \[points\]: LAZ chunk 0 declares more bytes than"
        ):
            bounded(read_cloud, tmp_path / name, max_bytes=2**20)
    # No items in the LASzip VLR: lazrs panicked (a BaseException) on this.
    vlr = laz.index(b"laszip encoded") - 2
    (tmp_path / "items.laz").write_bytes(_patched(laz, vlr + 54 + 32, "<H", 0))
    with pytest.raises(FileFormatError, match=r"items\.laz \[laszip\]: LASzip VLR without items"):
        read_cloud(tmp_path / "items.laz")
    (tmp_path / "table.laz").write_bytes(_patched(laz, offset, "<q", 2**40))
    with pytest.raises(FileFormatError, match=r"table\.laz \[chunk_table\]: chunk table at"):
        read_cloud(tmp_path / "table.laz")


def test_image_bombs(bases: dict[str, bytes], tmp_path: Path) -> None:
    png = bases["i.png"]
    path = tmp_path / "bomb.png"
    path.write_bytes(_patched(_patched(png, 16, ">I", 100_000), 20, ">I", 100_000))
    with pytest.raises(FileFormatError, match=r"bomb\.png \[size\]: PNG header declares 100000 x"):
        bounded(read_image, path, max_bytes=2**20)
    # Small in pixels but far more than a file of this size can hold.
    path.write_bytes(_patched(_patched(png, 16, ">I", 5000), 20, ">I", 5000))
    with pytest.raises(FileFormatError, match=r"bomb\.png \[size\]: PNG header declares 5000"):
        bounded(read_image, path, max_bytes=2**20)
    # An IDAT chunk claiming 2 GB: OpenCV allocated it (6 s) before failing.
    idat = png.index(b"IDAT") - 4
    path.write_bytes(_patched(png, idat, ">I", 2**31 - 1))
    with pytest.raises(FileFormatError, match=r"bomb\.png \[chunks\]: PNG chunk at byte 33"):
        bounded(read_image, path, max_bytes=2**20)
    jpg = bytearray(bases["i.jpg"])
    sof = jpg.index(b"\xff\xc0")
    struct.pack_into(">HH", jpg, sof + 5, 65535, 65535)
    (tmp_path / "bomb.jpg").write_bytes(bytes(jpg))
    with pytest.raises(FileFormatError, match=r"bomb\.jpg \[size\]: JPEG header declares 65535"):
        bounded(read_image, tmp_path / "bomb.jpg", max_bytes=2**20)
    bmp = bytearray(cv2.imencode(".bmp", np.zeros((4, 4), np.uint8))[1].tobytes())
    struct.pack_into("<ii", bmp, 18, 50_000, -50_000)
    (tmp_path / "bomb.bmp").write_bytes(bytes(bmp))
    with pytest.raises(FileFormatError, match=r"bomb\.bmp \[size\]: BMP header declares 50000"):
        bounded(read_image, tmp_path / "bomb.bmp", max_bytes=2**20)
    (tmp_path / "bomb.pgm").write_bytes(b"P5\n# big\n30000 30000\n255\n" + bytes(64))
    with pytest.raises(FileFormatError, match=r"bomb\.pgm \[size\]: PNM header declares 30000"):
        bounded(read_image, tmp_path / "bomb.pgm", max_bytes=2**20)
    tif = bytearray(cv2.imencode(".tiff", np.zeros((4, 4), np.uint8))[1].tobytes())
    ifd = struct.unpack_from("<I", tif, 4)[0]
    for k in range(struct.unpack_from("<H", tif, ifd)[0]):
        if struct.unpack_from("<H", tif, ifd + 2 + 12 * k)[0] in (256, 257):
            struct.pack_into("<HI", tif, ifd + 2 + 12 * k + 2, 4, 200_000)  # LONG 200000
            struct.pack_into("<I", tif, ifd + 2 + 12 * k + 8, 200_000)
    (tmp_path / "bomb.tif").write_bytes(bytes(tif))
    with pytest.raises(FileFormatError, match=r"bomb\.tif \[size\]: TIFF header declares 200000"):
        bounded(read_image, tmp_path / "bomb.tif", max_bytes=2**20)
    (tmp_path / "junk.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(40))
    with pytest.raises(FileFormatError, match=r"junk\.png: not an image OpenCV can decode"):
        read_image(tmp_path / "junk.png")


def test_read_bgr_checks_sizes(bases: dict[str, bytes], tmp_path: Path) -> None:
    from rough_map.near_far.tiles import read_bgr

    (tmp_path / "i.png").write_bytes(bases["i.png"])
    assert read_bgr(tmp_path / "i.png").shape == (24, 32, 3)
    png = bases["i.png"]
    (tmp_path / "bomb.png").write_bytes(_patched(_patched(png, 16, ">I", 10**5), 20, ">I", 10**5))
    with pytest.raises(FileFormatError, match=r"bomb\.png \[size\]"):
        read_bgr(tmp_path / "bomb.png")
    with pytest.raises(FileFormatError, match=r"none\.png: no such file"):
        read_bgr(tmp_path / "none.png")


def test_text_clouds(tmp_path: Path) -> None:
    (tmp_path / "long.csv").write_bytes(b"1," * 40_000 + b"1\n")
    with pytest.raises(FileFormatError, match=r"long\.csv \[text\]: line 1 is longer than 65536"):
        read_cloud(tmp_path / "long.csv")
    (tmp_path / "huge.csv").write_text("x,y,z\n1e999,2,3\n99999999999999999999999,5,6\n")
    np.testing.assert_array_equal(read_cloud(tmp_path / "huge.csv"), [[1e23, 5, 6]])
    (tmp_path / "junk.xyz").write_bytes(b"1 2 3\n\xff\xfe\x00 1 2\n")
    with pytest.raises(FileFormatError, match=r"junk\.xyz \[text\]: not a table of numbers"):
        bounded(read_cloud, tmp_path / "junk.xyz")
    (tmp_path / "poses.txt").write_text("1 2 3\n")
    with pytest.raises(FileFormatError, match=r"poses\.txt \[columns\]: expected 12 numbers"):
        read_kitti_poses(tmp_path / "poses.txt")


def test_ply_pcd_round_trips(tmp_path: Path) -> None:
    """Files open3d writes, in each of its forms, read back to the points."""
    for suffix in (".ply", ".pcd"):
        np.testing.assert_array_equal(read_cloud(write_cloud(tmp_path / f"w{suffix}", POINTS)),
                                      POINTS)  # fmt: skip
        for kwargs in ({}, {"write_ascii": True}, {"compressed": True}):
            path = tmp_path / f"legacy{suffix}"
            _open3d_legacy(path, POINTS, **kwargs)
            atol = 1e-4 if kwargs.get("write_ascii") else 1e-6
            np.testing.assert_allclose(read_cloud(path), POINTS, atol=atol, err_msg=str(kwargs))
        tensor = o3d.t.geometry.PointCloud(o3d.core.Tensor(POINTS.astype(np.float32)))
        tensor.point.intensity = o3d.core.Tensor(np.ones((len(POINTS), 1), np.float32))
        tensor.point.colors = o3d.core.Tensor(np.zeros((len(POINTS), 3), np.float32))
        for compressed in (False, True) if suffix == ".pcd" else (False,):
            path = tmp_path / f"tensor{suffix}"
            assert o3d.t.io.write_point_cloud(str(path), tensor, compressed=compressed)
            np.testing.assert_array_equal(read_cloud(path), POINTS.astype(np.float32))


def test_laz_of_a_regular_grid_reads(tmp_path: Path) -> None:
    """A rough regular grid compresses about 25 times in LAZ: under the declared-count bound."""
    grid = np.stack(np.meshgrid(np.arange(100) * 0.01, np.arange(100) * 0.01), -1).reshape(-1, 2)
    z = np.random.default_rng(0).normal(0, 0.01, len(grid))
    cloud = np.column_stack([grid, z])
    np.testing.assert_allclose(read_cloud(write_cloud(tmp_path / "g.laz", cloud)), cloud, atol=1e-4)
