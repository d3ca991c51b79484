"""A model and its card are committed together: a save killed at any moment leaves the old
pair, the new pair, or a state that the next save, load or card read turns into the new
pair; no pending or temporary file remains after it."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from rough_map import _files
from rough_map.classify import (
    load_terrain_model,
    read_card,
    save_terrain_model,
    sha256_file,
)
from rough_map.errors import ModelError


class Killed(BaseException):
    """Stands for SIGKILL: nothing after it runs, no cleanup that catches Exception."""


@pytest.fixture(scope="module")
def models():
    old = load_terrain_model("default")
    new = load_terrain_model("default")
    new.evidence_per_m_ = 2 * old.evidence_per_m_  # other bytes, same structure
    return old, new


@pytest.fixture(scope="module")
def new_files(models, tmp_path_factory) -> tuple[Path, Path]:
    """The files a save of the new model writes."""
    return save_terrain_model(models[1], tmp_path_factory.mktemp("new") / "m")


@pytest.fixture
def old_pair(models, tmp_path) -> tuple[Path, Path]:
    return save_terrain_model(models[0], tmp_path / "m")


def leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name not in ("m.skops", "m.card.json"))


def which(model_file: Path, models) -> str:
    """Which model the pair holds (loading also checks the file against its card)."""
    per_m = load_terrain_model(model_file).evidence_per_m_
    assert read_card(model_file)["sha256"] == sha256_file(model_file)
    return {models[0].evidence_per_m_: "old", models[1].evidence_per_m_: "new"}[per_m]


@pytest.mark.parametrize("kill_at", [0, 1])
def test_kill_between_the_renames(models, old_pair, new_files, monkeypatch, kill_at) -> None:
    model_file, _ = old_pair
    calls = []
    real = os.replace

    def replace(src, dst):
        calls.append(dst)
        if len(calls) == kill_at + 1:
            raise Killed
        return real(src, dst)

    monkeypatch.setattr(_files.os, "replace", replace)
    with pytest.raises(Killed):
        save_terrain_model(models[1], model_file.with_suffix(""))
    monkeypatch.setattr(_files.os, "replace", real)
    assert which(model_file, models) == "new"  # the load rolled it forward
    assert leftovers(model_file.parent) == []


@pytest.mark.parametrize("step", ["write_model", "write_card", "marker"])
def test_kill_while_staging_keeps_the_old_pair(
    models, old_pair, new_files, monkeypatch, step
) -> None:
    model_file, _ = old_pair
    real_fsync = _files.fsync_file

    def fsync(path: Path) -> None:
        real_fsync(path)
        names = {"write_model": "m.skops", "write_card": "m.card.json", "marker": "complete"}
        if path.name == names[step]:
            raise Killed

    monkeypatch.setattr(_files, "fsync_file", fsync)
    monkeypatch.setattr(shutil, "rmtree", lambda *a, **k: None)  # a kill cleans nothing
    with pytest.raises(Killed):
        save_terrain_model(models[1], model_file.with_suffix(""))
    monkeypatch.undo()
    pending = _files.pending_folder(model_file)
    assert pending.is_dir()
    # an incomplete commit (no marker) is discarded; a complete one is rolled forward
    expected = "new" if step == "marker" else "old"
    assert which(model_file, models) == expected
    assert leftovers(model_file.parent) == []


@pytest.mark.parametrize(
    ("staged", "moved", "marker", "expected"),
    [
        (["m.skops"], [], False, "old"),
        (["m.skops", "m.card.json"], [], False, "old"),
        (["m.skops", "m.card.json"], [], True, "new"),
        (["m.card.json"], ["m.skops"], True, "new"),
        ([], ["m.skops", "m.card.json"], True, "new"),
    ],
)
def test_every_interrupted_state_resolves(
    models, old_pair, new_files, staged, moved, marker, expected
) -> None:
    model_file, _ = old_pair
    folder = model_file.parent
    pending = _files.pending_folder(model_file)
    pending.mkdir()
    source = new_files[0].parent
    for name in staged:
        shutil.copy(source / name, pending / name)
    for name in moved:
        shutil.copy(source / name, folder / name)
    if marker:
        (pending / _files.MARKER).write_bytes(b"")
    assert which(model_file, models) == expected
    assert leftovers(folder) == []


def test_card_read_and_save_resolve_too(models, old_pair, new_files) -> None:
    model_file, card_file = old_pair
    pending = _files.pending_folder(model_file)
    pending.mkdir()
    for p in new_files:
        shutil.copy(p, pending / p.name)
    (pending / _files.MARKER).write_bytes(b"")
    assert read_card(card_file)["sha256"] == sha256_file(new_files[0])
    assert not pending.exists()
    pending.mkdir()
    (pending / "m.skops").write_bytes(b"partial")
    save_terrain_model(models[0], model_file.with_suffix(""))
    assert leftovers(model_file.parent) == []
    load_terrain_model(model_file)


def test_a_file_in_place_of_the_pending_folder(old_pair) -> None:
    model_file, _ = old_pair
    _files.pending_folder(model_file).write_text("x")
    with pytest.raises(ModelError, match="expected a pending-commit folder"):
        load_terrain_model(model_file)
