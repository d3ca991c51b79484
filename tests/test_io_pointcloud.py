"""Point-cloud readers and writers: round trips through the real libraries, real LAS files,
and every bad input turned into a FileFormatError that names the file and the field."""

from __future__ import annotations

import logging
from pathlib import Path

import laspy
import numpy as np
import open3d as o3d
import pytest
from laspy.vlrs.known import WktCoordinateSystemVlr

from rough_map._files import atomic_output
from rough_map.errors import FileFormatError, InputError
from rough_map.io.las import read_las
from rough_map.io.pointcloud import READERS, WRITERS, read_cloud, read_kitti_poses, write_cloud

DATA = Path(__file__).parent / "data"
US_FOOT = 1200 / 3937  # m


@pytest.fixture
def points() -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.uniform([-50, -50, -2], [50, 50, 3], size=(500, 3))


# --------------------------------------------------------------------------------------------
# Round trips


@pytest.mark.parametrize("suffix", sorted(WRITERS))
def test_write_read_round_trip(suffix: str, points: np.ndarray, tmp_path: Path) -> None:
    path = write_cloud(tmp_path / f"cloud{suffix}", points)
    got = read_cloud(path)
    assert got.dtype == np.float64 and got.shape == points.shape
    if suffix in (".las", ".laz"):
        np.testing.assert_allclose(got, points, atol=0.5e-4 + 1e-9)  # 0.1 mm integers
    else:
        np.testing.assert_array_equal(got, points)
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # no temporary file left


def test_upper_case_suffix(points: np.ndarray, tmp_path: Path) -> None:
    np.testing.assert_array_equal(read_cloud(write_cloud(tmp_path / "c.NPY", points)), points)


@pytest.mark.parametrize("suffix", [".ply", ".pcd"])
def test_read_files_written_by_open3d(suffix: str, points: np.ndarray, tmp_path: Path) -> None:
    legacy = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    path = tmp_path / f"legacy{suffix}"
    assert o3d.io.write_point_cloud(str(path), legacy, write_ascii=True)
    np.testing.assert_allclose(read_cloud(path), points, atol=1e-4)  # ASCII: 6 digits

    tensor = o3d.t.geometry.PointCloud(o3d.core.Tensor(points.astype(np.float32)))
    tensor.point.intensity = o3d.core.Tensor(np.ones((len(points), 1), np.float32))
    path = tmp_path / f"tensor{suffix}"
    assert o3d.t.io.write_point_cloud(str(path), tensor)
    np.testing.assert_array_equal(read_cloud(path), points.astype(np.float32))


def test_read_las_written_by_laspy(points: np.ndarray, tmp_path: Path) -> None:
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = [0.001, 0.001, 0.001]
    header.offsets = [1000.0, 2000.0, 0.0]
    las = laspy.LasData(header)
    las.x, las.y, las.z = points[:, 0] + 1000, points[:, 1] + 2000, points[:, 2]
    las.classification = np.arange(len(points)) % 3
    las.write(tmp_path / "laspy.las")
    cloud = read_las(tmp_path / "laspy.las")
    offset = np.array([1000.0, 2000.0, 0.0])
    np.testing.assert_allclose(cloud.points, points + offset, atol=0.5e-3 + 1e-9)
    np.testing.assert_array_equal(cloud.classification, np.arange(len(points)) % 3)
    assert cloud.crs is None


def test_read_numpy_variants(points: np.ndarray, tmp_path: Path) -> None:
    np.save(tmp_path / "xyzi.npy", np.column_stack([points, np.ones(len(points))]).astype("f4"))
    np.testing.assert_array_equal(read_cloud(tmp_path / "xyzi.npy"), points.astype("f4"))

    structured = np.zeros(len(points), dtype=[("t", "u4"), ("X", "f8"), ("y", "f8"), ("z", "f8")])
    structured["X"], structured["y"], structured["z"] = points.T
    np.save(tmp_path / "structured.npy", structured)
    np.testing.assert_array_equal(read_cloud(tmp_path / "structured.npy"), points)

    np.save(tmp_path / "ints.npy", np.arange(12, dtype=np.int16).reshape(4, 3))
    np.testing.assert_array_equal(read_cloud(tmp_path / "ints.npy"), np.arange(12).reshape(4, 3))


def test_read_text_variants(tmp_path: Path) -> None:
    expected = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.5]])
    (tmp_path / "plain.xyz").write_text("1 2 3\n4\t5  6.5\n")
    (tmp_path / "comments.txt").write_text("# scanner export\n\n1 2 3 0.5\n# gap\n4 5 6.5 0.7\n")
    (tmp_path / "named.csv").write_text("intensity,Z,X,Y\n9,3,1,2\n9,6.5,4,5\n")
    (tmp_path / "cloudcompare.txt").write_text("//X;Y;Z\n1;2;3\n4;5;6.5\n")
    for name in ("plain.xyz", "comments.txt", "named.csv", "cloudcompare.txt"):
        np.testing.assert_array_equal(read_cloud(tmp_path / name), expected, err_msg=name)


def test_kitti_scan_and_poses(points: np.ndarray, tmp_path: Path) -> None:
    scan = np.column_stack([points, np.full(len(points), 0.3)]).astype(np.float32)
    scan.tofile(tmp_path / "000000.bin")
    np.testing.assert_array_equal(read_cloud(tmp_path / "000000.bin"), scan[:, :3])

    (tmp_path / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n0 -1 0 1.5 1 0 0 -2 0 0 1 0.25\n")
    poses = read_kitti_poses(tmp_path / "poses.txt")
    assert poses.shape == (2, 4, 4)
    np.testing.assert_array_equal(poses[0], np.eye(4))
    np.testing.assert_array_equal(poses[1, :, 3], [1.5, -2.0, 0.25, 1.0])
    np.testing.assert_array_equal(poses[:, 3, :3], 0.0)


def test_nan_rows_dropped(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    cloud = np.array([[1.0, 2.0, 3.0], [np.nan, 0.0, 0.0], [0.0, np.inf, 0.0], [4.0, 5.0, 6.0]])
    np.save(tmp_path / "nan.npy", cloud)
    with caplog.at_level(logging.DEBUG, logger="rough_map"):
        got = read_cloud(tmp_path / "nan.npy")
    np.testing.assert_array_equal(got, cloud[[0, 3]])
    assert "dropped 2 of 4 points" in caplog.text


def test_finite_check_edge_cases(tmp_path: Path) -> None:
    """The check sums all coordinates first: a sum that overflows keeps every finite point,
    +inf and -inf (whose sum is NaN) are both dropped, float32 columns beyond z are ignored."""
    huge = np.full((4, 3), 1e308)
    np.save(tmp_path / "huge.npy", huge)
    np.testing.assert_array_equal(read_cloud(tmp_path / "huge.npy"), huge)
    cloud = np.array([[1.0, 2.0, 3.0], [np.inf, -np.inf, 0.0], [0.0, 0.0, -np.inf], [4, 5, 6]])
    np.save(tmp_path / "inf.npy", cloud)
    np.testing.assert_array_equal(read_cloud(tmp_path / "inf.npy"), cloud[[0, 3]])
    wide = np.ones((3, 4), dtype=np.float32)
    wide[:, 3] = np.nan  # an intensity column, not a coordinate
    np.save(tmp_path / "wide.npy", wide)
    got = read_cloud(tmp_path / "wide.npy")
    assert got.dtype == np.float64 and got.flags.c_contiguous
    np.testing.assert_array_equal(got, np.ones((3, 3)))


def test_atomic_write_keeps_old_file_on_failure(points: np.ndarray, tmp_path: Path) -> None:
    target = write_cloud(tmp_path / "c.las", points)
    before = target.read_bytes()
    bad = points.copy()
    bad[3, 1] = np.nan
    with pytest.raises(InputError, match="LAS cannot store NaN"):
        write_cloud(target, bad)
    assert target.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["c.las"]

    with pytest.raises(RuntimeError, match="boom"), atomic_output(tmp_path / "x.npy") as tmp:
        tmp.write_bytes(b"partial")
        raise RuntimeError("boom")
    assert [p.name for p in tmp_path.iterdir()] == ["c.las"]


# --------------------------------------------------------------------------------------------
# Real LAS files (laspy test data, see tests/data/README.md)


def test_read_real_las_with_crs() -> None:
    cloud = read_las(DATA / "ground_with_crs.las")
    assert cloud.points.shape == (25408, 3)
    assert np.count_nonzero(cloud.classification == 2) == 9808
    crs = cloud.crs
    assert crs is not None
    assert crs.wkt is not None and crs.wkt.startswith('PROJCS["NAD83_2011_Nebraska_ft"')
    assert crs.epsg == 32104  # ProjectedCSTypeGeoKey
    assert crs.horizontal_unit_m == pytest.approx(US_FOOT)  # WKT UNIT["Foot_US", ...]
    assert crs.vertical_unit_m == pytest.approx(US_FOOT)  # VerticalUnitsGeoKey 9003
    # The file spans 60 x 40 US survey feet.
    extent = cloud.points.max(axis=0) - cloud.points.min(axis=0)
    np.testing.assert_allclose(extent[:2], np.array([59.99, 39.98]) * US_FOOT, atol=1e-3)
    raw = laspy.read(DATA / "ground_with_crs.las")
    np.testing.assert_allclose(cloud.crs_coordinates()[:, 0], raw.x, rtol=1e-12)
    np.testing.assert_allclose(read_cloud(DATA / "ground_with_crs.las"), cloud.points)


def test_read_real_laz() -> None:
    cloud = read_las(DATA / "autzen_trim.laz")
    assert cloud.points.shape == (110000, 3)
    assert set(np.unique(cloud.classification)) == {1, 2}
    assert cloud.crs is not None
    assert cloud.crs.epsg is None  # user-defined Lambert conformal conic
    assert "Lambert_Conformal_Conic_2SP" in (cloud.crs.wkt or "")
    assert cloud.crs.horizontal_unit_m == cloud.crs.vertical_unit_m == 0.3048
    np.testing.assert_allclose(
        cloud.crs_coordinates(),
        np.column_stack([laspy.read(DATA / "autzen_trim.laz").xyz]),
        rtol=1e-12,
    )


def _las_with_wkt(path: Path, wkt: str) -> Path:
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.vlrs.append(WktCoordinateSystemVlr(wkt))
    las = laspy.LasData(header)
    las.x, las.y, las.z = np.array([1.0, 2.0]), np.array([3.0, 4.0]), np.array([5.0, 6.0])
    las.write(path)
    return path


def test_las_crs_variants(tmp_path: Path) -> None:
    compound = (
        'COMPD_CS["UTM 33N + NAVD88 ftUS",PROJCS["WGS 84 / UTM zone 33N",GEOGCS["WGS 84",'
        'DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]],PRIMEM["Greenwich",0],'
        'UNIT["degree",0.0174532925199433]],PROJECTION["Transverse_Mercator"],UNIT["metre",1],'
        'AUTHORITY["EPSG","32633"]],VERT_CS["NAVD88 height (ftUS)",VERT_DATUM["NAVD88",2005],'
        'UNIT["US survey foot",0.304800609601219],AXIS["Up",UP]]]'
    )
    cloud = read_las(_las_with_wkt(tmp_path / "compound.las", compound))
    assert cloud.crs is not None and cloud.crs.epsg == 32633
    np.testing.assert_allclose(cloud.points[:, :2], [[1.0, 3.0], [2.0, 4.0]], atol=1e-9)
    np.testing.assert_allclose(cloud.points[:, 2], np.array([5.0, 6.0]) * US_FOOT, atol=1e-9)

    wkt2 = (
        'PROJCRS["WGS 84 / UTM zone 33N",BASEGEOGCRS["WGS 84",DATUM["WGS 1984",'
        'ELLIPSOID["WGS 84",6378137,298.257223563,LENGTHUNIT["metre",1]]]],'
        'CONVERSION["UTM zone 33N",METHOD["Transverse Mercator",ID["EPSG",9807]]],'
        'CS[Cartesian,2],AXIS["(E)",east,LENGTHUNIT["metre",1]],'
        'AXIS["(N)",north,LENGTHUNIT["metre",1]],ID["EPSG",32633]]'
    )
    crs = read_las(_las_with_wkt(tmp_path / "wkt2.las", wkt2)).crs
    assert crs is not None and (crs.epsg, crs.horizontal_unit_m) == (32633, 1.0)

    geographic = (
        'GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]],'
        'PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433],AUTHORITY["EPSG","4326"]]'
    )
    with pytest.raises(FileFormatError, match=r"geographic\.las \[crs\]: geographic CRS"):
        read_las(_las_with_wkt(tmp_path / "geographic.las", geographic))


def test_las_unparsable_wkt_taken_as_metres(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = _las_with_wkt(tmp_path / "broken.las", 'PROJCS["broken"')
    with caplog.at_level(logging.WARNING, logger="rough_map"):
        cloud = read_las(path)
    assert cloud.crs is not None and cloud.crs.epsg is None
    assert cloud.crs.horizontal_unit_m == cloud.crs.vertical_unit_m == 1.0
    np.testing.assert_allclose(cloud.points[:, 2], [5.0, 6.0], atol=1e-9)
    assert "broken.las: could not parse the WKT of the CRS" in caplog.text
    assert "CRS without a linear unit; coordinates taken as m" in caplog.text


# --------------------------------------------------------------------------------------------
# Bad input


def test_unknown_suffix_and_missing_file(tmp_path: Path) -> None:
    (tmp_path / "cloud.foo").write_text("1 2 3\n")
    with pytest.raises(
        FileFormatError,
        match=r"cloud\.foo \[suffix\]: unknown point-cloud suffix '\.foo'; known: \.bin, \.csv",
    ):
        read_cloud(tmp_path / "cloud.foo")
    with pytest.raises(FileFormatError, match=r"missing\.npy: no such file"):
        read_cloud(tmp_path / "missing.npy")
    (tmp_path / "folder.npy").mkdir()
    with pytest.raises(FileFormatError, match=r"folder\.npy: not a regular file"):
        read_cloud(tmp_path / "folder.npy")


@pytest.mark.parametrize("suffix", sorted(READERS))
def test_empty_file(suffix: str, tmp_path: Path) -> None:
    path = tmp_path / f"empty{suffix}"
    path.touch()
    with pytest.raises(FileFormatError, match=rf"empty\{suffix}: the file is empty"):
        read_cloud(path)


def test_truncated_files(points: np.ndarray, tmp_path: Path) -> None:
    for suffix in (".npy", ".ply", ".pcd", ".las", ".laz"):
        path = write_cloud(tmp_path / f"full{suffix}", points)
        data = path.read_bytes()
        cut = tmp_path / f"cut{suffix}"
        cut.write_bytes(data[: len(data) * 2 // 3])
        with pytest.raises(FileFormatError, match=rf"cut\{suffix}"):
            read_cloud(cut)
    with pytest.raises(FileFormatError, match=r"truncated\?"):
        read_cloud(tmp_path / "cut.npy")
    with pytest.raises(FileFormatError, match=r"cut\.las: not a readable LAS/LAZ file \(truncated"):
        read_cloud(tmp_path / "cut.las")
    with pytest.raises(FileFormatError, match=r"cut\.ply \[points\]: truncated"):
        read_cloud(tmp_path / "cut.ply")
    for suffix in (".ply", ".pcd"):  # open3d fills the missing points of these without error
        ascii_cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        o3d.io.write_point_cloud(str(tmp_path / f"ascii{suffix}"), ascii_cloud, write_ascii=True)
        data = (tmp_path / f"ascii{suffix}").read_bytes()
        (tmp_path / f"ascii{suffix}").write_bytes(data[: len(data) // 2])
        with pytest.raises(FileFormatError, match=rf"ascii\{suffix} \[points\]: truncated"):
            read_cloud(tmp_path / f"ascii{suffix}")
    # A LAS cut at a record boundary reads without a laspy error: the point count tells.
    data = (tmp_path / "full.las").read_bytes()
    (tmp_path / "cut.las").write_bytes(data[: len(data) - 100 * 30])  # 30 B per format-6 record
    with pytest.raises(FileFormatError, match=r"cut\.las \[points\]: truncated: 400 of the 500"):
        read_cloud(tmp_path / "cut.las")
    (tmp_path / "cut.bin").write_bytes(np.zeros(10, np.float32).tobytes())
    with pytest.raises(
        FileFormatError, match=r"cut\.bin \[size\]: size 40 B is not a multiple of 16"
    ):
        read_cloud(tmp_path / "cut.bin")


def test_wrong_shape(tmp_path: Path) -> None:
    np.save(tmp_path / "xy.npy", np.zeros((10, 2)))
    with pytest.raises(FileFormatError, match=r"xy\.npy \[shape\]: .*got shape \(10, 2\)"):
        read_cloud(tmp_path / "xy.npy")
    np.save(tmp_path / "flat.npy", np.zeros(9))
    with pytest.raises(FileFormatError, match=r"\[shape\]: .*got shape \(9,\)"):
        read_cloud(tmp_path / "flat.npy")
    (tmp_path / "xy.csv").write_text("x,y\n1,2\n3,4\n")
    with pytest.raises(FileFormatError, match=r"xy\.csv \[shape\]"):
        read_cloud(tmp_path / "xy.csv")
    np.save(tmp_path / "none.npy", np.zeros((0, 3)))
    with pytest.raises(FileFormatError, match=r"none\.npy \[points\]: the file holds no points"):
        read_cloud(tmp_path / "none.npy")
    structured = np.zeros(3, dtype=[("x", "f4"), ("y", "f4")])
    np.save(tmp_path / "noz.npy", structured)
    with pytest.raises(FileFormatError, match=r"noz\.npy \[z\]: structured array without"):
        read_cloud(tmp_path / "noz.npy")


def test_wrong_dtype(tmp_path: Path) -> None:
    np.save(tmp_path / "str.npy", np.array([["a", "b", "c"], ["d", "e", "f"]]))
    with pytest.raises(
        FileFormatError, match=r"str\.npy \[dtype\]: expected numbers, got dtype <U1"
    ):
        read_cloud(tmp_path / "str.npy")
    np.save(tmp_path / "obj.npy", np.array([[1, "b", None]], dtype=object), allow_pickle=True)
    with pytest.raises(FileFormatError, match=r"obj\.npy: not a readable \.npy file.*allow_pickle"):
        read_cloud(tmp_path / "obj.npy")
    (tmp_path / "words.csv").write_text("x,y,z\n1,2,3\n4,five,6\n")
    with pytest.raises(
        FileFormatError, match=r"words\.csv \[row 2, column 2\]: not a table of numbers"
    ):
        read_cloud(tmp_path / "words.csv")
    (tmp_path / "binary.txt").write_bytes(b"\x00\xff\xfe garbage \x81\x82\n" * 4)
    with pytest.raises(FileFormatError, match=r"binary\.txt.*not a table of numbers"):
        read_cloud(tmp_path / "binary.txt")


def test_all_nan(tmp_path: Path) -> None:
    np.save(tmp_path / "nan.npy", np.full((5, 3), np.nan))
    with pytest.raises(
        FileFormatError, match=r"nan\.npy \[xyz\]: all 5 points are NaN or infinite"
    ):
        read_cloud(tmp_path / "nan.npy")
    (tmp_path / "nan.csv").write_text("nan,nan,nan\nnan,1,2\n")
    with pytest.raises(FileFormatError, match=r"nan\.csv \[xyz\]: all 2 points"):
        read_cloud(tmp_path / "nan.csv")


def test_corrupt_ply_and_pcd(tmp_path: Path) -> None:
    (tmp_path / "bad.ply").write_text("ply\nformat ascii 1.0\nelement vertex 5\n")
    with pytest.raises(FileFormatError, match=r"bad\.ply \[header\]: no end_header line"):
        read_cloud(tmp_path / "bad.ply")
    (tmp_path / "bad.pcd").write_bytes(b"\x00" * 64)
    with pytest.raises(FileFormatError, match=r"bad\.pcd \[header\]: no DATA line"):
        read_cloud(tmp_path / "bad.pcd")
    (tmp_path / "bad.las").write_bytes(b"LASF" + b"\x00" * 300)
    with pytest.raises(FileFormatError, match=r"bad\.las"):
        read_cloud(tmp_path / "bad.las")


def test_kitti_poses_errors(tmp_path: Path) -> None:
    (tmp_path / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1\n")
    with pytest.raises(FileFormatError, match=r"poses\.txt \[columns\]: expected 12 numbers"):
        read_kitti_poses(tmp_path / "poses.txt")
    (tmp_path / "empty.txt").write_text("# nothing\n")
    with pytest.raises(FileFormatError, match=r"empty\.txt \[poses\]: the file holds no poses"):
        read_kitti_poses(tmp_path / "empty.txt")


def test_write_errors(points: np.ndarray, tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"\(N, 3\) array .* got shape \(500, 2\)"):
        write_cloud(tmp_path / "c.npy", points[:, :2])
    with pytest.raises(InputError, match="non-empty"):
        write_cloud(tmp_path / "c.npy", np.empty((0, 3)))
    with pytest.raises(FileFormatError, match=r"c\.bin \[suffix\]: cannot write suffix '\.bin'"):
        write_cloud(tmp_path / "c.bin", points)
    with pytest.raises(FileFormatError, match=r"cannot write: folder .* does not exist"):
        write_cloud(tmp_path / "missing" / "c.npy", points)
    with pytest.raises(InputError, match="too wide for LAS"):
        write_cloud(tmp_path / "wide.las", np.array([[0.0, 0.0, 0.0], [1e6, 0.0, 0.0]]))
