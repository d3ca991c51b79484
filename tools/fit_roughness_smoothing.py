"""Learn the roughness smoother's noise model from the simulator's training traverses.

Simulates :data:`TRAINING` (four 48 m ``random`` courses of all five surfaces, at 0.3 to
0.7 m/s, with range sensors of 6 to 20 points per cell and 0.3 to 1.5 mm noise), computes
their features with the default extraction, fits
:class:`rough_map.filter.RoughnessSmoother` and prints the YAML of
``configs/roughness_smoothing.yaml`` (``--write`` writes it there). About 4 minutes and
2 GB of memory on a 2-core machine; the clouds (about 0.6 GB) go to a temporary folder
unless ``--keep DIR``.

``tests/test_roughness_smoothing.py::test_shipped_noise_model_is_reproduced`` runs the
same and compares with the shipped file, so that it cannot go stale.

    python tools/fit_roughness_smoothing.py [--write] [--keep DIR]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import yaml

#: The training traverses: seed, speed (m/s), points per 8 mm cell, range noise (m).
TRAINING: tuple[tuple[int, float, float, float], ...] = (
    (201, 0.3, 12.0, 0.0005),
    (202, 0.5, 6.0, 0.001),
    (203, 0.7, 20.0, 0.0003),
    (204, 0.5, 8.0, 0.0015),
)
#: Course length, m (built whole: <= 50 m).
LENGTH = 48.0

HEADER = """\
# Smoothing of ln R and w along the path (rough_map.filter.RoughnessSmoother): a Kalman
# filter and RTS smoother with a random-walk ground and jumps where the ground changes
# (see rough_map/filter/roughness.py). Read by rough_map.filter.load_roughness_smoother().
#
# process_noise   variance of ln R (R in m^3/rad) and of w added per metre travelled, 1/m
# measurement     one frame's ln R and w about its ground: standard deviations, correlation
#                 (for frames farther apart than error_length)
# error_length    m over which consecutive frames share their error (overlapping patches,
#                 roughness varying over metres), for its two uncorrelated parts: the log
#                 PSD level at the fit's pivot (ln R + kappa w, kappa = -cov/var(w) from
#                 measurement) and w; a frame adding s m of ground counts as
#                 min(1, s / error_length) of a measurement of each
# jump            size of a change of ground: standard deviations of the change of ln R and
#                 w, correlation
# alpha           false-alarm probability of the jump test of one onset (chi2, 2 dof)
# window          m the jump test looks back for the onset of a change
# min_process_noise  lower bound on the process noise learnt, 1/m
#
# Learnt by `python tools/fit_roughness_smoothing.py --write` from four simulated 48 m
# random courses (tests/test_roughness_smoothing.py checks that it still comes out so).
"""


def simulate_training(folder: Path, *, keep: bool = True) -> Iterator[Path]:
    """Simulate :data:`TRAINING` into ``folder``, one traverse at a time; yields each
    traverse folder. Unless ``keep``, a folder simulated here is removed once the caller
    has moved on to the next (a traverse's clouds take about 250 MB)."""
    from rough_map.simulate.course import SensorSpec, simulate

    for seed, speed, density, noise in TRAINING:
        path = folder / f"rs-train-{seed}"
        made = False
        if not (path / "traverse.json").is_file():
            simulate(
                path,
                "random",
                length=LENGTH,
                speed=speed,
                seed=seed,
                images=False,
                sensor=SensorSpec(points_per_cell=density, noise=noise),
                compress=True,
            )
            made = True
        yield path
        if made and not keep:
            shutil.rmtree(path, ignore_errors=True)


def fit(folder: Path, *, keep: bool = True) -> tuple[Any, dict[str, Any]]:
    """The fitted smoother of the training traverses (simulated into ``folder`` if not
    there yet, and removed again after their features unless ``keep``) and its config
    mapping."""
    from rough_map.features import traverse_features
    from rough_map.filter import RoughnessSmoother

    tables = [traverse_features(p) for p in simulate_training(folder, keep=keep)]
    smoother = RoughnessSmoother().fit(tables)
    training = {
        "traverses": [
            f"random {LENGTH:g} m, seed {s}, {v} m/s, {d:g} points/cell, {n * 1e3:g} mm noise"
            for s, v, d, n in TRAINING
        ],
        "stretches": int(smoother.n_segments_),
        "changes": int(smoother.n_changes_),
        "frames": int(sum(len(t) for t in tables)),
    }
    return smoother, smoother.to_config(training)


def config_text(config: dict[str, Any]) -> str:
    """The YAML of ``configs/roughness_smoothing.yaml`` (rounded to 4 significant digits)."""

    def rounded(value: Any) -> Any:
        if isinstance(value, float):
            return float(f"{value:.4g}")
        if isinstance(value, dict):
            return {k: rounded(v) for k, v in value.items()}
        if isinstance(value, list):
            return [rounded(v) for v in value]
        return value

    body = yaml.safe_dump(rounded(config), sort_keys=False, allow_unicode=True, width=100)
    return HEADER + "\n" + body


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--write", action="store_true", help="write configs/roughness_smoothing.yaml")
    p.add_argument("--keep", type=Path, help="simulate into (or reuse) this folder")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="rs-train-") as tmp:
        folder = args.keep or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        _, config = fit(folder, keep=args.keep is not None)
    text = config_text(config)
    if args.write:
        target = Path(__file__).resolve().parents[1] / "configs" / "roughness_smoothing.yaml"
        target.write_text(text, encoding="utf-8")
        print(f"wrote {target}", file=sys.stderr)
    else:
        print(text, end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
