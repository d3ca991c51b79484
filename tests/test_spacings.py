"""A model classifies frames read at any step of the auto ladder (issue 29, item 5).

A traverse too sparse for the model's 8 mm grid is read on a coarser one (spacing auto,
from the model's step up); :func:`rough_map.classify.on_model_grid` moves that grid's
spectrum onto the model's wavenumbers (the same ``2 pi k / L`` up to the coarser grid's
``pi / B``) and corrects it for what the two grids do to the ground (the estimator's own
leakage, cell-mean and lateral tables). Checked here on a Gaussian power law and on three
kinds of ground outside that family, then end to end with the default model on sparse
simulated traverses.
"""

from __future__ import annotations

import csv
import json
import types
from functools import cache

import numpy as np
import pytest
from surfaces import bilinear, power_law_field, real_like_surface

from rough_map.classify import SpectralFeatures, feature_matrix, on_model_grid
from rough_map.cli.main import main
from rough_map.errors import ModelError
from rough_map.features import cloud_roughness
from rough_map.patch import Extraction, PatchSpec, spacing_ladder
from rough_map.simulate.course import SensorSpec, simulate

SPEC = PatchSpec()
LADDER = spacing_ladder(SPEC)
#: The model's band of spectrum features (SpectralFeatures' omega_max 160 rad/m): k <= 22.
BAND = 22


@cache
def ground(kind: str):
    if kind == "gaussian":
        field = power_law_field(1024, 0.004, 1e-5, -2.5, seed=3)
        return lambda x, y: field.sample(x, y, order=1)
    grid = real_like_surface(kind, 0)
    return lambda x, y: bilinear(grid, x, y)


def dense_cloud(kind: str, origin: tuple[float, float], seed: int) -> np.ndarray:
    """12 random points per 8 mm cell over the patch, with 0.3 mm of noise."""
    rng = np.random.default_rng(seed)
    side = SPEC.n * SPEC.spacing
    count = rng.poisson(12 * (1.1 * side / SPEC.spacing) ** 2)
    x, y = (rng.uniform(-0.05 * side, 1.05 * side, count) for _ in range(2))
    z = ground(kind)(origin[0] + x, origin[1] + y) + 0.0003 * rng.standard_normal(count)
    return np.column_stack([x + SPEC.x0, y + SPEC.y0, z])


def one_frame(r) -> types.SimpleNamespace:
    """The table-like view :func:`on_model_grid` reads of one reading."""
    columns = {"w": np.array([r.w]), "lateral_scale": np.array([r.lateral_scale])}
    return types.SimpleNamespace(
        omega=r.omega, log_psd=np.log10(r.psd)[None], columns=columns, name="t"
    )


@pytest.mark.parametrize("kind", ["gaussian", "blocks", "boulders", "smooth"])
@pytest.mark.parametrize("step", [1, 2, 3])
def test_a_coarser_grid_maps_onto_the_model_grid(kind: str, step: int) -> None:
    """The same cloud read at 11.2, 16 and 22.4 mm, mapped onto the 8 mm wavenumbers,
    gives the 8 mm spectrum over the model's band: median 0.003-0.029 dex measured, where
    the unmapped spectra are 0.019-0.167 dex off (printed under -s)."""
    mapped, raw = [], []
    for i, origin in enumerate([(0.1, 0.1), (1.3, 1.9)]):
        cloud = dense_cloud(kind, origin, seed=i)
        _, fine = cloud_roughness(cloud, Extraction())
        _, coarse = cloud_roughness(cloud, Extraction(patch=LADDER[step]))
        top = min(BAND, coarse.omega.size)
        ref = np.log10(fine.psd[:top])
        grid = on_model_grid(one_frame(coarse), fine.omega)
        assert grid.shape == (1, fine.omega.size) and np.isnan(grid[0, coarse.omega.size :]).all()
        mapped.append(grid[0, :top] - ref)
        raw.append(np.log10(coarse.psd[:top]) - ref)
    err, before = np.median(np.abs(mapped)), np.median(np.abs(raw))
    print(
        f"{kind} {LADDER[step].spacing * 1e3:.1f} mm: mapped {err:.3f}, unmapped {before:.3f} dex"
    )
    assert err <= 0.035, f"{kind} at {LADDER[step].spacing * 1e3:.1f} mm: {err:.3f} dex"
    assert err <= before / 2.5, (err, before)


def test_the_model_grid_itself_is_kept_and_another_patch_refused() -> None:
    _, r = cloud_roughness(dense_cloud("blocks", (0.4, 0.4), seed=5), Extraction())
    frame = one_frame(r)
    assert np.array_equal(on_model_grid(frame, r.omega), frame.log_psd)
    other = 2 * np.pi * np.arange(1, 57) / 1.0  # a 1 m patch
    with pytest.raises(
        ModelError,
        match=r"from 7.01 rad/m, not the multiples of the model's 6.28 rad/m.*patch of 1 m",
    ):
        on_model_grid(frame, other)


def test_spectral_features_leave_out_the_ordinates_a_coarse_grid_lacks() -> None:
    """A spectrum that ends inside the band is measured on what it has, as ordinates below
    the noise floor are; one with nothing in the band has no features."""
    rng = np.random.default_rng(0)
    omega = 2 * np.pi * np.arange(1, 57) / 0.896
    X = np.column_stack(
        [np.log10(1e-5 * omega**-2.5)[None, :] + 0.1 * rng.standard_normal((40, 56))]
    )
    sf = SpectralFeatures(omega=omega, scalars=()).fit(X)
    cut = X.copy()
    cut[:, 20:] = np.nan  # a 22.4 mm grid's spectrum ends at 140 rad/m: k <= 20
    whole, part = sf.transform(X), sf.transform(cut)
    assert np.isfinite(part).all()
    names = list(sf.get_feature_names_out())
    for name in ("level", "slope"):
        j = names.index(name)
        assert np.median(np.abs(part[:, j] - whole[:, j])) < 0.05
    gone = X.copy()
    gone[:, :BAND] = np.nan
    assert np.isnan(sf.transform(gone)).all()


@cache
def sparse_traverse(tmp: str, per_cell: float, seed: int) -> str:
    out = f"{tmp}/sparse_{per_cell}_{seed}"
    sensor = SensorSpec(points_per_cell=per_cell)
    simulate(out, "mixed", length=24.0, seed=seed, images=False, sensor=sensor)
    return out


@pytest.fixture(scope="module")
def tmp_dir(tmp_path_factory: pytest.TempPathFactory) -> str:
    return str(tmp_path_factory.mktemp("spacings"))


@pytest.mark.slow
@pytest.mark.parametrize("seed", [21, 22, 23])
@pytest.mark.parametrize("per_cell", [1.0, 0.5])
def test_the_default_model_classifies_a_sparse_traverse(
    tmp_dir: str, per_cell: float, seed: int, capsys
) -> None:
    """1 and 0.5 points per 8 mm cell: refused before (every frame 'too many gaps'), now
    read on the 11.2 and 16 mm grids and classified. Measured on 24 m mixed courses, seeds
    21-23 (printed under -s): raw 0.70-0.85 / filtered 0.90-0.96 at 1 point per cell, raw
    0.73-0.76 / filtered 0.80-0.96 at 0.5 (the training sensors' 12 points: 0.86 / 0.99).
    R and w are not mapped: on ground that is not a power law they move with their band."""
    traverse = sparse_traverse(tmp_dir, per_cell, seed)
    labels = f"{tmp_dir}/labels_{per_cell}_{seed}.csv"
    assert main(["-q", "classify", traverse, "--model", "default", "--out", labels]) == 0
    with open(labels, newline="") as f:
        rows = list(csv.DictReader(f))
    assert all(r["raw_class"] for r in rows), "every frame is read and classified"
    filtered = np.mean([r["filtered_class"] == r["label"] for r in rows])
    raw = np.mean([r["raw_class"] == r["label"] for r in rows])
    with capsys.disabled():  # the figures the README quotes, under -s
        print(f"{per_cell} points per cell, seed {seed}: raw {raw:.3f}, filtered {filtered:.3f}")
    assert filtered >= 0.75 and raw >= 0.65, (raw, filtered)
    if seed != 21:
        return
    out = f"{tmp_dir}/map_{per_cell}"
    capsys.readouterr()
    assert main(["-q", "map", traverse, "--out", out, "--no-png", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["valid"] == summary["frames"] and summary["near_class_accuracy"] >= 0.75
    with open(f"{out}/features.csv.json") as f:
        omega = json.load(f)["omega_rad_per_m"]
    assert len(omega) < 56, "read on a coarser grid than the model's"


@pytest.mark.slow
def test_frames_too_sparse_for_any_grid_have_no_class(tmp_dir: str, capsys) -> None:
    """Frames no step reads get no class (not the filter's prior); a traverse where none is
    read fails with their reason rather than writing labels of nothing."""
    import shutil
    from pathlib import Path

    sparse = Path(f"{tmp_dir}/holes")
    shutil.copytree(sparse_traverse(tmp_dir, 1.0, 21), sparse)
    clouds = sorted((sparse / "clouds").glob("*.npy"))
    for cloud in clouds[10:16]:  # six frames of 0.05 points per cell
        points = np.load(cloud)
        np.save(cloud, points[::20])
    labels = f"{tmp_dir}/labels_holes.csv"
    assert main(["-q", "classify", str(sparse), "--out", labels]) == 0
    with open(labels, newline="") as f:
        rows = list(csv.DictReader(f))
    empty = [
        i for i, r in enumerate(rows) if not (r["raw_class"] or r["filtered_class"] or r["level"])
    ]
    assert empty == list(range(10, 16)), empty
    capsys.readouterr()
    traverse = sparse_traverse(tmp_dir, 0.05, 21)
    assert main(["-q", "classify", traverse, "--out", f"{tmp_dir}/none.csv"]) == 2
    err = capsys.readouterr().err
    assert "none of its" in err and "frames has a valid patch" in err and len(err.splitlines()) == 1


def test_feature_matrix_on_the_model_grid_keeps_the_scalars(mixed_table) -> None:
    X, names = feature_matrix(mixed_table, omega=mixed_table.omega)
    Y, _ = feature_matrix(mixed_table)
    assert np.array_equal(X, Y, equal_nan=True) and names[-1] == f"psd_{mixed_table.omega.size:02d}"


@pytest.fixture(scope="module")
def mixed_table(tmp_dir: str):
    from rough_map.features import traverse_features

    out = f"{tmp_dir}/mixed"
    simulate(out, "mixed", length=6.0, seed=4, images=False, sensor=SensorSpec(points_per_cell=6.0))
    return traverse_features(out)


@cache
def _captif_errors(step: int) -> tuple[float, float]:
    """Median |dex| of the CAPTIF scan's spectrum read at ``LADDER[step]``, mapped and not,
    against its 8 mm reading (12 points per 8 mm cell, six places along the scan)."""
    from test_density import CAPTIF_STARTS, captif_cloud

    mapped, raw = [], []
    for i, start in enumerate(CAPTIF_STARTS):
        cloud = captif_cloud(start, 12, seed=i)
        _, fine = cloud_roughness(cloud, Extraction())
        _, coarse = cloud_roughness(cloud, Extraction(patch=LADDER[step]))
        top = min(BAND, coarse.omega.size)
        ref = np.log10(fine.psd[:top])
        mapped.append(on_model_grid(one_frame(coarse), fine.omega)[0, :top] - ref)
        raw.append(np.log10(coarse.psd[:top]) - ref)
    return float(np.median(np.abs(mapped))), float(np.median(np.abs(raw)))


@pytest.mark.parametrize("step", [1, 2, 3])
def test_the_real_chipseal_scan_mapped_stays_near_its_grid(step: int) -> None:
    """The CAPTIF chipseal (real, the same across the patch, its power at millimetre
    wavelengths): mapped within 0.07-0.15 dex of the 8 mm spectrum, measured, where
    unmapped it is 0.07-0.13 off."""
    err, before = _captif_errors(step)
    print(
        f"CAPTIF {LADDER[step].spacing * 1e3:.1f} mm: mapped {err:.3f}, unmapped {before:.3f} dex"
    )
    assert err <= 0.2


@pytest.mark.xfail(strict=True, reason="issue 29: the mapping does not help on the chipseal")
@pytest.mark.parametrize("step", [1, 2, 3])
def test_the_mapping_helps_on_the_real_chipseal_too(step: int) -> None:
    """What it does on four synthetic kinds of ground (2.5 x closer) it does not on the real
    scan: the grids differ there by texture folded in from above their Nyquist, which the
    power-law tables, read at the w of the coarse band, do not describe."""
    err, before = _captif_errors(step)
    assert err <= before / 2.5
