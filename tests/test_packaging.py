"""The package carries what it needs: a built wheel holds the default model, its card and the
configs, and ``rough-map map`` runs from it without ``--model``.

The wheel is installed into a fresh venv without its dependencies; the fresh venv borrows
them from the running environment through a ``.pth`` line (a plain path, so the running
environment's editable install of rough_map is not picked up), which keeps the test to
seconds while rough_map itself is imported from the wheel only.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import sysconfig
import venv
import zipfile
from pathlib import Path

import pytest

from rough_map.classify import RoughnessLevels, load_roughness_levels
from rough_map.classify.persistence import load_terrain_model, read_card
from rough_map.errors import InputError
from rough_map.resources import config_file, model_base, shipped_models

ROOT = Path(__file__).resolve().parents[1]


def test_shipped_files_are_the_top_level_ones() -> None:
    assert shipped_models() == ["default"]
    base = model_base()
    assert base.with_suffix(".skops").read_bytes() == (ROOT / "models/default.skops").read_bytes()
    for name in ("roughness_levels.yaml", "stereo.yaml"):
        assert config_file(name).read_bytes() == (ROOT / "configs" / name).read_bytes()


def test_a_users_model_beside_the_shipped_one_is_not_shipped(tmp_path, monkeypatch) -> None:
    """``train --out models/mine`` in a checkout writes beside the shipped model: it is not
    listed as shipped nor found by its bare name (and pyproject packs only the default)."""
    import shutil

    from rough_map import resources

    for suffix in (".skops", ".card.json"):
        shutil.copy(model_base().with_suffix(suffix), tmp_path / f"default{suffix}")
        shutil.copy(model_base().with_suffix(suffix), tmp_path / f"mine{suffix}")
    monkeypatch.setattr(resources, "_folder", lambda name: tmp_path)
    assert resources.shipped_models() == ["default"]
    with pytest.raises(InputError, match=r"no shipped model named 'mine' \(shipped: default\)"):
        resources.model_base("mine")
    pyproject = (Path(__file__).resolve().parents[1] / "pyproject.toml").read_text()
    assert '"models/default.skops", "models/default.card.json"' in pyproject


def test_bare_model_name_loads_the_shipped_model(tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)  # no models/ here: the name must come from the package
    model = load_terrain_model("default")
    assert list(model.classes_) == read_card(model_base().with_suffix(".card.json"))["classes"]


def test_unknown_model_name_lists_the_shipped_ones(tmp_path, monkeypatch) -> None:
    from rough_map.errors import ModelError

    monkeypatch.chdir(tmp_path)
    with pytest.raises(ModelError, match=r"no such model file .*shipped with rough_map: default"):
        load_terrain_model("nosuchmodel")
    with pytest.raises(InputError, match="no shipped model named 'x'"):
        model_base("x")


def test_levels_default_is_the_shipped_config() -> None:
    assert load_roughness_levels(None) == RoughnessLevels()


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    build = tmp_path_factory.mktemp("build")
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--no-build-isolation",
            "--disable-pip-version-check",
            "-q",
            "-w",
            str(out),
            str(ROOT),
        ],
        check=True,
        cwd=build,
        env={**os.environ, "PIP_NO_INPUT": "1"},
    )
    (whl,) = out.glob("rough_map-*.whl")
    return whl


def test_wheel_holds_models_and_configs(wheel: Path) -> None:
    names = set(zipfile.ZipFile(wheel).namelist())
    for name in (
        "rough_map/models/default.skops",
        "rough_map/models/default.card.json",
        "rough_map/configs/roughness_levels.yaml",
        "rough_map/configs/stereo.yaml",
        "rough_map/data/leakage_tables.npz",
        "rough_map/py.typed",
    ):
        assert name in names, name
    # The README's pictures stay out of the wheel.
    assert not any(n.startswith("rough_map/data/readme/") for n in names)


def test_map_runs_from_an_installed_wheel_without_model(wheel: Path, tmp_path: Path) -> None:
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=False).create(env_dir)
    py = env_dir / "bin" / "python"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "--python",
            str(py),
            "install",
            "--no-deps",
            "--disable-pip-version-check",
            "-q",
            str(wheel),
        ],
        check=True,
    )
    site = subprocess.run(
        [str(py), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    # Borrow the dependencies (not rough_map) from this environment.
    deps = sysconfig.get_path("purelib")
    (Path(site) / "_borrowed_deps.pth").write_text(deps + "\n")

    work = tmp_path / "work"  # not the checkout: nothing may be found through it
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    exe = env_dir / "bin" / "rough-map"
    where = subprocess.run(
        [str(py), "-c", "import rough_map; print(rough_map.__file__)"],
        check=True,
        capture_output=True,
        text=True,
        cwd=work,
        env=env,
    ).stdout.strip()
    assert Path(where).is_relative_to(site), where

    run = lambda *a: subprocess.run(  # noqa: E731
        [str(exe), *a], cwd=work, env=env, capture_output=True, text=True, timeout=600
    )
    sim = run(
        "-q",
        "simulate",
        "--out",
        "t",
        "--course",
        "compact",
        "--length",
        "2.5",
        "--no-images",
        "--seed",
        "3",
    )
    assert sim.returncode == 0, sim.stderr
    res = run("map", "t", "--out", "m", "--no-png", "--json")
    assert res.returncode == 0, res.stderr
    summary = json.loads(res.stdout)
    assert summary["valid"] > 0
    assert (work / "m" / "map.tif").is_file()
    assert (work / "m" / "labels.csv").is_file()
    named = run("classify", "t", "--model", "default", "--out", "labels.csv")
    assert named.returncode == 0, named.stderr
