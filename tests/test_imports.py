"""Heavy third-party packages are imported where the work needs them, not at start-up.

``rough-map CMD --help`` and ``import rough_map.workflow`` must not wait for OpenCV, open3d,
matplotlib, rasterio, rosbags, laspy or skops; reading an .npy cloud needs neither open3d
nor laspy. A fresh interpreter runs the steps one after the other and reports, after each,
which of these packages are loaded; a LAS read at the end shows that the report sees an
import when one happens.

scikit-learn is the one exception for the library (not for the CLI's start-up): the
estimators (``TerrainModel``, ``SpectralFeatures``, the path filter, the near-to-far
classifier) subclass ``sklearn.base.BaseEstimator``, so their modules import it.
"""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys

import numpy as np
import pytest

from rough_map.io.pointcloud import write_cloud

HEAVY = ("cv2", "laspy", "matplotlib", "open3d", "rasterio", "rosbags", "skops", "sklearn")

#: Needed by the class definitions of the estimators (see the module docstring).
LIBRARY_ALLOWS = {"sklearn"}

_STEPS = r"""
import contextlib, importlib, io, json, pathlib, sys

HEAVY = set(sys.argv[1].split(","))


def report(step):
    print(json.dumps([step, sorted({m.split(".")[0] for m in sys.modules} & HEAVY)]), flush=True)


from rough_map.cli.main import main

with contextlib.redirect_stdout(io.StringIO()):
    for command in ("map", "features"):
        assert main([command, "--help"]) == 0, command
report("cli_help")

import rough_map.workflow

report("workflow")

from rough_map.io.pointcloud import read_cloud

assert read_cloud(sys.argv[2]).shape == (50, 3)
report("read_npy")

package = pathlib.Path(rough_map.__file__).parent
for path in sorted(package.rglob("*.py")):
    parts = path.relative_to(package.parent).with_suffix("").parts
    if parts[-1] != "__main__":
        importlib.import_module(".".join(parts).removesuffix(".__init__"))
report("all_modules")

assert read_cloud(sys.argv[3]).shape == (50, 3)
report("read_las")
"""


@pytest.fixture(scope="module")
def loaded(tmp_path_factory: pytest.TempPathFactory) -> dict[str, set[str]]:
    """Step name -> the heavy packages loaded after it, in a fresh interpreter."""
    folder = tmp_path_factory.mktemp("imports")
    cloud = np.random.default_rng(0).uniform(-1, 1, size=(50, 3))
    npy, las = write_cloud(folder / "c.npy", cloud), write_cloud(folder / "c.las", cloud)
    done = subprocess.run(
        [sys.executable, "-c", _STEPS, ",".join(HEAVY), str(npy), str(las)],
        capture_output=True,
        text=True,
        cwd=folder,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    steps = [json.loads(line) for line in done.stdout.splitlines() if line.startswith("[")]
    return {name: set(packages) for name, packages in steps}


def test_help_loads_no_heavy_package(loaded: dict[str, set[str]]) -> None:
    assert loaded["cli_help"] == set()


def test_workflow_loads_only_scikit_learn(loaded: dict[str, set[str]]) -> None:
    assert loaded["workflow"] <= LIBRARY_ALLOWS


def test_reading_npy_needs_no_backend(loaded: dict[str, set[str]]) -> None:
    assert loaded["read_npy"] == loaded["workflow"]


def test_no_module_imports_a_backend_at_import(loaded: dict[str, set[str]]) -> None:
    """Every module of the package imported: OpenCV, open3d, matplotlib ... stay out."""
    assert loaded["all_modules"] <= LIBRARY_ALLOWS


def test_report_sees_an_import(loaded: dict[str, set[str]]) -> None:
    """Reading a LAS file does import laspy, and the report says so."""
    assert loaded["read_las"] - loaded["all_modules"] == {"laspy"}


def test_heavy_names_are_importable() -> None:
    """The names checked are the packages' real import names (a typo would pass silently)."""
    assert [n for n in HEAVY if importlib.util.find_spec(n) is None] == []
