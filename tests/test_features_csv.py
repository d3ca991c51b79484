"""features.csv is formatted a column at a time: the same text as formatting each value."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np
import pytest

from rough_map.errors import FileFormatError
from rough_map.features import FeatureTable, read_features, write_features
from rough_map.features.files import _column_text, _fmt
from rough_map.features.table import COLUMNS, INT_COLUMNS, TEXT_COLUMNS


def test_column_text_is_each_value_formatted() -> None:
    columns = [
        np.array([0.1, -2.5e-7, np.nan, np.inf, -np.inf, 1e300, 0.0, -0.0, 123456789.123]),
        np.array([1.5, np.nan], dtype=np.float32),
        np.array([True, False, True]),
        np.array([0, -3, 2**40], dtype=np.int64),
        np.array([7, 0], dtype=np.uint8),
        np.array(["", "A", "gravel", None, 2.5, True], dtype=object),
        np.array(["a", "b"]),
        [1, 2.5, 1234567890, True, "x"],  # a list: each value as it is
    ]
    for values in columns:
        assert _column_text(values) == [_fmt(v) for v in values]
        assert _column_text(values[1:]) == [_fmt(v) for v in values[1:]]


def _table(n: int) -> FeatureTable:
    rng = np.random.default_rng(4)
    cols: dict[str, np.ndarray] = {}
    for c in COLUMNS:
        if c in TEXT_COLUMNS:
            cols[c] = np.array([f"{c}{i % 3}" if i % 4 else "" for i in range(n)], dtype=object)
        elif c in INT_COLUMNS:
            cols[c] = np.arange(n) * 7
        elif c == "valid":
            cols[c] = rng.random(n) > 0.3
        else:
            v = rng.normal(0, 10, n) * 10.0 ** rng.integers(-8, 8, n)
            v[rng.random(n) < 0.1] = np.nan
            cols[c] = v
    omega = np.array([1.0, 2.0, 4.0])
    log_psd = rng.normal(-6, 1, (n, 3))
    return FeatureTable(cols, omega, log_psd, "t")


def test_features_csv_is_the_row_by_row_text(tmp_path: Path) -> None:
    """2,500 rows (more than a block of rows formatted at once): each line is the row's
    values formatted one by one, and the table reads back."""
    table = _table(2500)
    path = write_features(table, tmp_path / "features.csv")
    names = list(COLUMNS) + table.spectrum_names()
    data = dict(table.columns)
    for k, name in enumerate(table.spectrum_names()):
        data[name] = table.log_psd[:, k]
    want = io.StringIO(newline="")
    writer = csv.writer(want)
    writer.writerow(names)
    for i in range(len(table)):
        writer.writerow([_fmt(data[c][i]) for c in names])
    assert path.read_bytes() == want.getvalue().encode("utf-8")
    back = read_features(path)
    assert np.allclose(back["R"], table["R"], rtol=1e-8, atol=0, equal_nan=True)  # 9 digits
    assert list(back["label"]) == list(table["label"])


def test_a_table_without_its_metadata_is_one_short_line(tmp_path: Path) -> None:
    """fuzz seed 23 (read_features): this message was 224 characters with its path."""
    path = write_features(_table(3), tmp_path / "features.csv")
    path.with_name("features.csv.json").unlink()
    with pytest.raises(FileFormatError, match=r"metadata file features\.csv\.json is missing") as e:
        read_features(path)
    assert len(str(e.value)) - len(str(path)) <= 150


class _Killed(BaseException):
    """A kill (nothing after it runs)."""


@pytest.mark.parametrize("kill_at", [0, 1, 2])
def test_a_table_and_its_metadata_change_together(tmp_path: Path, monkeypatch, kill_at) -> None:
    """One set (issue 31): killed before, between or after the renames of features.csv and
    features.csv.json, the next read finds the whole old pair or the whole new one, and no
    pending folder stays."""
    import os
    import shutil

    from rough_map import _files

    path = tmp_path / "features.csv"
    old, new = _table(5), _table(8)
    write_features(old, path)
    real = os.replace
    calls: list[str] = []

    def replace(src, dst):
        calls.append(str(dst))
        if len(calls) == kill_at + 1 and kill_at < 2:
            raise _Killed
        return real(src, dst)

    monkeypatch.setattr(_files.os, "replace", replace)
    monkeypatch.setattr(shutil, "rmtree", lambda *a, **k: None)  # a kill cleans nothing
    if kill_at < 2:
        with pytest.raises(_Killed):
            write_features(new, path)
    else:
        write_features(new, path)
    monkeypatch.undo()
    back = read_features(path)  # finishes the commit; a mismatched pair would warn
    assert len(back) == len(new)  # the marker was written before the first rename
    assert not list(tmp_path.glob(".*"))


def test_a_write_killed_while_staging_keeps_the_old_pair(tmp_path: Path, monkeypatch) -> None:
    import shutil

    from rough_map import _files

    path = tmp_path / "features.csv"
    write_features(_table(5), path)
    real = _files.fsync_file

    def fsync(p):
        real(p)
        if Path(p).name == "features.csv.json":
            raise _Killed

    monkeypatch.setattr(_files, "fsync_file", fsync)
    monkeypatch.setattr(shutil, "rmtree", lambda *a, **k: None)
    with pytest.raises(_Killed):
        write_features(_table(8), path)
    monkeypatch.undo()
    assert len(read_features(path)) == 5 and not list(tmp_path.glob(".*"))


def test_an_old_pending_commit_does_not_outlive_its_set(tmp_path: Path) -> None:
    """A folder replaced as a set (rough-map map --out) does not carry an old run's pending
    commit over: rolled forward later, it would put the old table back."""
    import shutil

    from rough_map import _files
    from rough_map._files import output_set

    out = tmp_path / "run"
    out.mkdir()
    write_features(_table(5), out / "features.csv")
    pending = _files.pending_folder(out / "features.csv")
    pending.mkdir()  # a complete commit of the old run, killed before its renames
    for name in ("features.csv", "features.csv.json"):
        shutil.copy(out / name, pending / name)
    (pending / _files.MARKER).write_bytes(b"")
    with output_set(out, owned=("features.csv", "features.csv.json")) as stage:
        write_features(_table(8), stage / "features.csv")
    assert not pending.exists() and len(read_features(out / "features.csv")) == 8
