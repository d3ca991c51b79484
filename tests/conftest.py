from pathlib import Path

import numpy as np
import pytest

from rough_map import terrain
from rough_map.types import HeightField


@pytest.fixture
def dense_cloud():
    """A dense (about 40 points per 8 mm cell) noisy cloud over gravel, vehicle frame."""

    def make(name="gravel", n_points=500_000, noise=0.0005, seed=0, spacing=0.004):
        h = terrain.generate(name, (300, 400), spacing, seed=seed)
        hf = HeightField(h, spacing, origin=(0.3, -0.6))
        rng = np.random.default_rng(seed + 1)
        x = rng.uniform(0.52, 1.48, n_points)
        y = rng.uniform(-0.48, 0.48, n_points)
        z = hf.sample(x, y) + rng.normal(0, noise, n_points)
        return np.column_stack([x, y, z])

    return make


@pytest.fixture(autouse=True, scope="session")
def _user_models_in_a_temporary_folder(tmp_path_factory):
    """Models trained by name go to a folder of the test session, not the user's."""
    import os

    folder = tmp_path_factory.mktemp("user_models")
    saved = os.environ.get("ROUGH_MAP_MODELS")
    os.environ["ROUGH_MAP_MODELS"] = str(folder)
    yield folder
    if saved is None:
        os.environ.pop("ROUGH_MAP_MODELS", None)
    else:
        os.environ["ROUGH_MAP_MODELS"] = saved


@pytest.fixture(autouse=True)
def _restore_cli_logging():
    """``rough_map.cli.main.main`` configures the 'rough_map' logger; undo it per test."""
    import logging

    logger = logging.getLogger("rough_map")
    saved = logger.handlers[:], logger.level, logger.propagate
    yield
    logger.handlers[:], logger.level, logger.propagate = saved


# -- simulated traverses shared by the test modules (one build per test session and worker) --


@pytest.fixture(scope="session")
def small_traverse(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 3 m mixed course, clouds only (about 8 frames, 2 points per 8 mm cell). Read-only:
    tests write their outputs elsewhere."""
    from rough_map.simulate.course import SensorSpec, simulate

    out = tmp_path_factory.mktemp("sim") / "small"
    simulate(out, "mixed", length=3.0, seed=1, images=False, sensor=SensorSpec(points_per_cell=2))
    return out


@pytest.fixture(scope="session")
def imaged_traverse(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``rough-map simulate --out D --course mixed --length 6 --image-every 3 --seed 1``: a
    mixed course with a stereo pair every third frame. Read-only."""
    from rough_map.cli.main import main

    out = tmp_path_factory.mktemp("sim") / "imaged"
    assert main(["-q", "simulate", "--out", str(out), "--course", "mixed", "--length", "6",
                 "--image-every", "3", "--seed", "1"]) == 0  # fmt: skip
    return out
