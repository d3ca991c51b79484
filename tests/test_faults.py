"""Faults while writing: full disk, read-only folder, a write failing half way, leftovers.

The outputs of a command are a set (:func:`rough_map._files.output_set`): after a failure the old
set is there byte for byte, with no temporary file, and the error is one line naming the
file. The full-disk and read-only cases mount a small tmpfs / a read-only bind mount (as
root); they are skipped where mounting is not permitted.
"""

from __future__ import annotations

import errno
import hashlib
import logging
import os
import shutil
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from rough_map._files import (
    atomic_output,
    clean_stale,
    gdal_errors,
    is_temp_name,
    output_set,
    recover,
    verify_file,
)
from rough_map.cli.main import main
from rough_map.errors import FileFormatError
from rough_map.io.traverse import load_traverse

MAP_ARGS = ["--no-png", "--near-far", "off"]


def _hashes(folder: Path) -> dict[str, str]:
    return {
        p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def _temps(*folders: Path) -> list[str]:
    return [p.name for f in folders if f.is_dir() for p in f.rglob("*") if is_temp_name(p.name)]


@pytest.fixture(scope="module")
def old_map(small_traverse: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A complete ``rough-map map --no-png`` output of the small traverse (read-only)."""
    out = tmp_path_factory.mktemp("old") / "out"
    assert main(["-q", "map", str(small_traverse), "--out", str(out), *MAP_ARGS]) == 0
    return out


def _mount(*args: str) -> None:
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting needs root and mount(8)")
    done = subprocess.run(["mount", *args], capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"mount {' '.join(args)} is not permitted here: {done.stderr.strip()}")


def _umount(path: Path) -> None:
    subprocess.run(["umount", "-l", str(path)], capture_output=True)


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A 1 MB tmpfs: room for an old map output, not for the GeoTIFF writer's work."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    _mount("-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mnt))
    try:
        yield mnt
    finally:
        _umount(mnt)


def _one_error_line(err: str, path: Path) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("rough-map map: error: ") and str(path) in lines[0], err
    assert len(lines[0]) < 300
    return lines[0]


# ----------------------------------------------------------------------------- full disk


def test_map_on_a_full_disk_keeps_the_old_outputs(
    small_traverse: Path, old_map: Path, small_disk: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = small_disk / "out"
    shutil.copytree(old_map, out)
    (out / "notes.txt").write_text("mine\n")
    before = _hashes(out)
    code = main(["-q", "map", str(small_traverse), "--out", str(out), *MAP_ARGS])
    line = _one_error_line(capsys.readouterr().err, out)
    assert code == 2
    assert "No space left on device" in line and ".tmp." not in line
    assert _hashes(out) == before
    assert _temps(small_disk) == [] and sorted(os.listdir(small_disk)) == ["out"]


def test_features_pair_on_a_full_disk_keeps_the_old_pair(
    small_traverse: Path, old_map: Path, small_disk: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    table = small_disk / "features.csv"
    shutil.copy(old_map / "features.csv", table)
    shutil.copy(old_map / "features.csv.json", small_disk / "features.csv.json")
    before = _hashes(small_disk)
    free = shutil.disk_usage(small_disk).free
    with open(small_disk / "filler", "wb") as fh:  # leave room for the metadata only
        fh.write(b"\0" * max(0, free - 6 * 1024))
    code = main(["-q", "features", str(small_traverse), "--out", str(table)])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1, err
    assert f"{table}" in err and "cannot write: No space left on device" in err
    (small_disk / "filler").unlink()
    assert _hashes(small_disk) == before
    assert _temps(small_disk) == []


# ----------------------------------------------------------------------------- read-only


def test_map_into_a_read_only_folder_is_one_line(
    small_traverse: Path, old_map: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    ro = tmp_path / "ro"
    shutil.copytree(old_map, ro / "out")
    before = _hashes(ro)
    _mount("--bind", str(ro), str(ro))
    try:
        _mount("-o", "remount,ro,bind", str(ro))
        out = ro / "out"
        code = main(["-q", "map", str(small_traverse), "--out", str(out), *MAP_ARGS])
        line = _one_error_line(capsys.readouterr().err, out)
        assert code == 2 and "Read-only file system" in line
    finally:
        _umount(ro)
    assert _hashes(ro) == before and _temps(ro) == []


def test_map_into_a_bind_mount_of_the_same_file_system(
    small_traverse: Path, old_map: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A bind mount on the parent's own device: os.path.ismount misses it, and swapping it
    gave ``cannot write: Device or resource busy``; its files are now replaced one by one."""
    source, out = tmp_path / "source", tmp_path / "out"
    shutil.copytree(old_map, source)
    (source / "notes.txt").write_text("mine\n")
    out.mkdir()
    _mount("--bind", str(source), str(out))
    try:
        assert not os.path.ismount(out)  # the case: same device as its parent
        code = main(["-q", "map", str(small_traverse), "--out", str(out), *MAP_ARGS])
        assert code == 0, capsys.readouterr().err
        assert (out / "notes.txt").read_text() == "mine\n" and _temps(out) == []
    finally:
        _umount(out)
    assert _hashes(source).keys() == _hashes(old_map).keys() | {"notes.txt"}


# ------------------------------------------------------------ a write failing half way


def test_a_failure_half_way_leaves_the_old_set(
    small_traverse: Path, old_map: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import rough_map.workflow as wf

    out = tmp_path / "out"
    shutil.copytree(old_map, out)
    before = _hashes(out)

    def no_room(*args: object, **kwargs: object) -> None:  # after the GeoTIFFs
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(wf, "write_tables", no_room)
    result = wf.analyse(load_traverse(small_traverse), near_far=False)
    with pytest.raises(FileFormatError, match=r"out: cannot write: No space left on device$"):
        wf.write_outputs(result, out, png=False)
    assert _hashes(out) == before
    assert _temps(tmp_path) == []


def test_the_set_is_swapped_whole_and_keeps_the_users_files(
    small_traverse: Path, old_map: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import rough_map._files as outset

    out = tmp_path / "out"
    shutil.copytree(old_map, out)
    (out / "map_old_layer.png").write_bytes(b"an old output")  # ours, not written again
    (out / "notes.txt").write_text("mine\n")
    (out / "mine").mkdir()
    (out / "mine" / "a.txt").write_text("also mine\n")
    # the fallback (rename aside, rename in) where RENAME_EXCHANGE is missing
    monkeypatch.setattr(outset, "exchange", lambda a, b: False)
    assert main(["-q", "map", str(small_traverse), "--out", str(out), *MAP_ARGS]) == 0
    assert not (out / "map_old_layer.png").exists()
    assert (out / "notes.txt").read_text() == "mine\n"
    assert (out / "mine" / "a.txt").read_text() == "also mine\n"
    new = _hashes(out)
    del new["notes.txt"], new["mine/a.txt"]
    assert new == _hashes(old_map)  # a rerun gives the same bytes
    assert sorted(os.listdir(tmp_path)) == ["out"]


def test_verify_refuses_a_truncated_geotiff(old_map: Path, tmp_path: Path) -> None:
    data = (old_map / "map.tif").read_bytes()
    target = tmp_path / "map.tif"
    target.write_bytes(b"old")
    with pytest.raises(FileFormatError, match=r"map.tif: cannot write: the GeoTIFF does not"):
        with atomic_output(target) as tmp:
            tmp.write_bytes(data[: len(data) // 2])
    assert target.read_bytes() == b"old" and os.listdir(tmp_path) == ["map.tif"]
    good = tmp_path / "good.tif"
    good.write_bytes(data)
    verify_file(good, good)  # a whole one passes


def test_verify_refuses_an_empty_file(tmp_path: Path) -> None:
    with pytest.raises(FileFormatError, match=r"a.json: cannot write: the file came out empty"):
        with atomic_output(tmp_path / "a.json") as tmp:
            tmp.touch()
    assert os.listdir(tmp_path) == []


def test_gdal_errors_printed_without_raising_are_errors(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "map.tif"
    with pytest.raises(FileFormatError, match=r"map.tif: cannot write: No space left on device$"):
        with gdal_errors(path):
            os.write(2, b"_tiffWriteProc: No space left on device.\n")
    with gdal_errors(path):
        os.write(2, b"Warning 1: something harmless\n")
    assert capfd.readouterr().err == "Warning 1: something harmless\n"


def test_rasterio_errors_become_one_line(tmp_path: Path) -> None:
    import rasterio

    path = tmp_path / "missing" / "x.tif"
    with pytest.raises(FileFormatError, match=r"x.tif: cannot write: ") as info:
        with gdal_errors(path):
            rasterio.open(path, "w", driver="GTiff", width=1, height=1, count=1, dtype="uint8")
    assert "\n" not in str(info.value)


# -------------------------------------------------------------------------- leftovers


def _age(path: Path) -> None:
    old = time.time() - 3600
    os.utime(path, (old, old))


def test_stale_temporaries_are_removed_by_the_next_run(
    small_traverse: Path, old_map: Path, tmp_path: Path
) -> None:
    out = tmp_path / "out"
    shutil.copytree(old_map, out)
    stale = [
        out / ".map.0123456789ab.tmp.tif",
        out / ".map.0123456789ab.tmp.src.tif",
        out / ".features.csv.0123456789ab.tmp.json",
    ]
    for p in stale:
        p.write_bytes(b"half")
        _age(p)
    staged = tmp_path / ".out.tmp.0123456789ab"
    staged.mkdir()
    (staged / "map.tif").write_bytes(b"half")
    _age(staged)
    live = tmp_path / ".out.tmp.fedcba987654"  # a run going on now: kept
    live.mkdir()
    os.utime(live, (time.time() + 3600,) * 2)
    (out / ".notes.txt").write_text("a hidden file of the user\n")
    assert main(["-q", "map", str(small_traverse), "--out", str(out), *MAP_ARGS]) == 0
    assert sorted(os.listdir(tmp_path)) == [".out.tmp.fedcba987654", "out"]
    assert _temps(out) == [] and (out / ".notes.txt").is_file()


def test_clean_stale_takes_only_our_names(tmp_path: Path) -> None:
    names = [".a.0123456789ab.tmp.csv", ".a.csv.tmp", "a.0123456789ab.tmp.csv", ".b.tmp.x"]
    for n in names:
        (tmp_path / n).write_text("x")
        _age(tmp_path / n)
    assert clean_stale(tmp_path) == 1
    assert sorted(os.listdir(tmp_path)) == sorted(names[1:])


def test_a_folder_set_aside_by_a_killed_run_is_put_back(tmp_path: Path) -> None:
    aside = tmp_path / ".out.old.0123456789ab"
    aside.mkdir()
    (aside / "map.tif").write_bytes(b"old set")
    _age(aside)
    staged = tmp_path / ".out.tmp.0123456789ab"  # the new set, never renamed in
    staged.mkdir()
    _age(staged)
    recover(tmp_path / "out")
    assert sorted(os.listdir(tmp_path)) == ["out"]
    assert (tmp_path / "out" / "map.tif").read_bytes() == b"old set"


def test_output_set_commit_and_failure(tmp_path: Path) -> None:
    out = tmp_path / "out"
    with output_set(out, owned=("*.csv",)) as stage:
        (stage / "a.csv").write_text("1\n")
        (stage / "b.csv").write_text("1\n")
    (out / "user.txt").write_text("u\n")
    with pytest.raises(FileFormatError, match=r"out/c.csv: cannot write: boom"):
        with output_set(out, owned=("*.csv",)) as stage:
            (stage / "a.csv").write_text("2\n")
            raise FileFormatError(stage / "c.csv", "cannot write: boom")
    assert sorted(os.listdir(out)) == ["a.csv", "b.csv", "user.txt"]
    assert (out / "a.csv").read_text() == "1\n"
    with output_set(out, owned=("*.csv",)) as stage:
        (stage / "a.csv").write_text("3\n")
    assert sorted(os.listdir(out)) == ["a.csv", "user.txt"]  # b.csv: the old run's
    assert (out / "a.csv").read_text() == "3\n" and sorted(os.listdir(tmp_path)) == ["out"]


def test_features_metadata_ties_the_pair(
    old_map: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from rough_map.features import read_features

    for name in ("features.csv", "features.csv.json"):
        shutil.copy(old_map / name, tmp_path / name)
    table = read_features(tmp_path / "features.csv")
    assert "table_sha256" in (tmp_path / "features.csv.json").read_text()
    assert "written with" not in caplog.text
    data = (tmp_path / "features.csv").read_bytes()
    (tmp_path / "features.csv").write_bytes(data.replace(b"\r\n", b"\n", 1))  # edited
    with caplog.at_level(logging.WARNING, logger="rough_map"):
        read_features(tmp_path / "features.csv")
    assert "is not the table its metadata features.csv.json was written with" in caplog.text
    assert np.all(np.isfinite(table.omega))


def test_the_current_folder_is_written_file_by_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "a.csv").write_text("old\n")
    (out / "b.csv").write_text("old\n")
    monkeypatch.chdir(out)  # cannot be renamed under the user's feet
    with output_set(out, owned=("*.csv",)) as stage:
        assert stage.parent == out
        (stage / "a.csv").write_text("new\n")
    assert sorted(os.listdir(out)) == ["a.csv"] and (out / "a.csv").read_text() == "new\n"


def test_batch_failing_at_the_fused_map_keeps_the_old_top_and_the_done_traverse(
    small_traverse: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import rough_map.batch as batch_mod

    out = tmp_path / "batch"
    batch_mod.run_batch([small_traverse], out, png=False, near_far=False)
    (out / "notes.txt").write_text("mine\n")
    name = next(p.name for p in out.iterdir() if p.is_dir())
    (out / name / "map_state.npz").unlink()  # to be mapped again
    before_top = {k: v for k, v in _hashes(out).items() if "/" not in k}

    def no_room(*args: object, **kwargs: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(batch_mod, "export_map", no_room)
    with pytest.raises(FileFormatError, match=r"batch: cannot write: No space left on device$"):
        batch_mod.run_batch([small_traverse], out, png=False, near_far=False)
    assert {k: v for k, v in _hashes(out).items() if "/" not in k} == before_top
    assert (out / name / "map_state.npz").is_file()  # the traverse is done: not redone
    assert _temps(tmp_path) == []
    monkeypatch.undo()
    again = batch_mod.run_batch([small_traverse], out, png=False, near_far=False)
    assert again.skipped == [name] and (out / "notes.txt").read_text() == "mine\n"
    assert _hashes(out) == {**_hashes(out), **before_top}


def test_a_file_name_the_system_refuses_is_one_line(tmp_path: Path, capsys) -> None:
    """A name longer than the file system allows (ENAMETOOLONG) or with a NUL byte is a
    FileFormatError naming it, not an OSError (the fuzzer found the first)."""
    from rough_map.io.pointcloud import read_cloud

    with pytest.raises(FileFormatError, match="cannot be read: File name too long"):
        read_cloud(tmp_path / ("x" * 300 + ".npy"))
    with pytest.raises(FileFormatError, match=r"cannot be read: .*null"):
        read_cloud(Path(str(tmp_path / "a\0b.npy")))
    assert main(["features", str(tmp_path / ("y" * 300 + ".npy"))]) == 2
    err = capsys.readouterr().err
    assert "File name too long" in err and "Traceback" not in err and len(err.splitlines()) == 1


def test_height_samples_of_points_at_absurd_coordinates() -> None:
    """Points beyond any world (1e300 m, 1e18 m) are left out of a frame's height sample
    rather than overflowing its cell index; far-apart cells keep their own sums."""
    from rough_map.features.frames import height_sample

    class Job:
        pose = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)

    pts = np.array([[1e300, 0, 5], [1e18, 1e18, 5], [0.05, 0.05, 2.0], [0.06, 0.01, 4.0]])
    h = height_sample(pts, Job(), 0.1, 8000)
    assert (h.rows.tolist(), h.cols.tolist(), h.sums.tolist(), h.counts.tolist()) == (
        [0],
        [0],
        [6.0],
        [2.0],
    )
    far = np.array([[9e8, 9e8, 1.0], [-9e8, -9e8, 3.0]])
    h = height_sample(far, Job(), 0.001, 8000)  # 1.8e12 cells a side: keyed by pairs
    assert sorted(zip(h.rows.tolist(), h.sums.tolist(), strict=True)) == [
        (-9 * 10**11, 3.0),
        (9 * 10**11, 1.0),
    ]
