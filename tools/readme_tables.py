"""Generators of the README's measured tables (used by ``tools/readme_check.py --tables``).

Each generator runs the documented commands (``rough-map simulate``, ``rough-map evaluate
--json``, ``rough-map map --json``) on simulated courses the default model never saw and
returns the Markdown table rows the README shows.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

EXE = [sys.executable, "-m", "rough_map"]

#: (course cell, sensor cell, simulate runs) of the model-accuracy table.
ACCURACY_ROWS: list[tuple[str, str, list[dict[str, object]]]] = [
    ("mixed 36 m (21)", "default, 0.5 m/s", [{"course": "mixed", "length": 36, "seed": 21}]),
    (
        "mixed-reverse 36 m (22)",
        "default, 0.5 m/s",
        [{"course": "mixed-reverse", "length": 36, "seed": 22}],
    ),
    (
        "random 80 m (23, 24)",
        "default, 0.5 m/s",
        [
            {"course": "random", "length": 80, "seed": 23},
            {"course": "random", "length": 80, "seed": 24},
        ],
    ),
    (
        "mixed 36 m (31)",
        "6 points/cell, 1 mm noise, 0.3 m/s",
        [
            {
                "course": "mixed",
                "length": 36,
                "seed": 31,
                "points-per-cell": 6,
                "noise": 0.001,
                "speed": 0.3,
            }
        ],
    ),
    (
        "mixed-reverse 36 m (32)",
        "default, 0.7 m/s",
        [{"course": "mixed-reverse", "length": 36, "seed": 32, "speed": 0.7}],
    ),
    (
        "compact 22 m (33), ploughed 42 m (34)",
        "default, 0.5 m/s",
        [{"course": "compact", "seed": 33}, {"course": "ploughed", "seed": 34}],
    ),
    (
        "random 60 m (35)",
        "20 points/cell, 0.2 mm noise",
        [
            {
                "course": "random",
                "length": 60,
                "seed": 35,
                "points-per-cell": 20,
                "noise": 0.0002,
            }
        ],
    ),
    (
        "mixed 24 m (0), the demo's course",
        "default, 0.5 m/s",
        [{"course": "mixed", "length": 24, "seed": 0, "width": 6}],
    ),
]


def _run(args: list[str], cwd: Path) -> str:
    proc = subprocess.run([*EXE, *args], cwd=cwd, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"rough-map {' '.join(args)} failed: {proc.stderr.strip()}")
    return proc.stdout


def _one(
    sim: dict[str, object], work: Path, log: Callable[[str], None]
) -> tuple[int, float, float, float]:
    name = "_".join(f"{k}{v}" for k, v in sim.items())
    out = work / name
    opts = [a for k, v in sim.items() for a in (f"--{k}", str(v))]
    log(f"  simulate {' '.join(opts)}")
    _run(["-q", "simulate", "--out", str(out), "--no-images", *opts], work)
    ev = json.loads(_run(["-q", "evaluate", str(out), "--model", "default", "--json"], work))
    mp = json.loads(
        _run(["-q", "map", str(out), "--out", str(out / "map"), "--no-png", "--json"], work)
    )
    frames = int(sum(sum(r) for r in ev["raw"]["confusion_matrix"]))
    return frames, ev["raw"]["accuracy"], ev["filtered"]["accuracy"], mp["near_class_accuracy"]


def accuracy_table(log: Callable[[str], None]) -> str:
    """The default model on unseen simulated courses: frame accuracy and map cells."""
    rows = [
        "| course (seed) | sensor, speed | frames | raw | filtered | near-field map cells |",
        "|---|---|---|---|---|---|",
    ]
    with tempfile.TemporaryDirectory(prefix="readme_tables_") as tmp:
        for course, sensor, sims in ACCURACY_ROWS:
            res = [_one(s, Path(tmp), log) for s in sims]
            cells = [
                " + ".join(str(r[0]) for r in res),
                ", ".join(f"{r[1]:.2f}" for r in res),
                ", ".join(f"{r[2]:.2f}" for r in res),
                ", ".join(f"{r[3]:.3f}" for r in res),
            ]
            rows.append(f"| {course} | {sensor} | " + " | ".join(cells) + " |")
    return "\n".join(rows) + "\n"


def density_table(log: Callable[[str], None]) -> str:
    """The same ground at every density (``tests/test_density.py`` measures and checks it):
    synthetic power-law surfaces against the exact reading, and the CAPTIF scan against its
    own 50-points-per-cell reading and against its exact 8 mm reading."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    import numpy as np
    import test_density as d

    def cell(values: list[float]) -> str:
        return " / ".join(f"{v:+.2f}" for v in values)

    rows = [
        "| points per 8 mm cell | grid (`--spacing auto`) | median ln(R/R_exact), "
        "w = -2.0 / -2.4 / -2.8 | median w - w_exact | median abs ln(R/R_exact) |",
        "|---|---|---|---|---|",
    ]

    def row(label: str, step: float | None, errs: list) -> str:
        """One row: signed medians of ln R and w, and median |ln R|, per waviness."""
        grid = "none" if step is None else f"{step * 1e3:.1f} mm"
        return (
            f"| {label} | {grid} | "
            + cell([float(np.median(e[:, 0])) for e in errs])
            + " | "
            + cell([float(np.median(e[:, 1])) for e in errs])
            + " | "
            + " / ".join(f"{float(np.median(np.abs(e[:, 0]))):.2f}" for e in errs)
            + " |"
        )

    for per_cell, auto in ((50, False), (12, False), (4, False), (2, True), (1, True), (0.5, True)):
        log(f"density: {per_cell} points per cell")
        errs = [d.errors(w, per_cell, auto) for w in d.WAVINESS]
        step = d.auto_spacing(int(per_cell * d.SPEC.n**2), d.SPEC).spacing if auto else 0.008
        rows.append(row(f"{per_cell:g}", step, errs))
    for spec in d.spacing_ladder(d.SPEC)[1:4]:
        log(f"density: exact patches on the {spec.spacing * 1e3:.1f} mm grid")
        errs = [d.band_errors(w, spec) for w in d.WAVINESS]
        rows.append(row("exact (the band alone)", spec.spacing, errs))
    log("density: the ground's own R and w")
    rows.append(row("the ground's true R and w", None, [d.truth_errors(w) for w in d.WAVINESS]))
    ref = d.captif_readings(50)
    for per_cell in (100, 20, 12, 4, 2, 1, 0.5):
        log(f"density: CAPTIF at {per_cell} points per cell")
        got = d.captif_readings(per_cell)
        rows.append(
            f"| CAPTIF, {per_cell:g} | {_grid(got)} | "
            f"{np.median(got[:, 0] - ref[:, 0]):+.2f} (vs 50 points per cell) | "
            f"{np.median(got[:, 1] - ref[:, 1]):+.2f} | "
            f"{np.median(np.abs(got[:, 0] - ref[:, 0])):.2f} |"
        )
    rows += _captif_exact_rows(log)
    return "\n".join(rows) + "\n"


def _captif_exact_rows(log: Callable[[str], None]) -> list[str]:
    """The CAPTIF scan against its exact 8 mm reading (``tests/test_lateral.py``): clouds
    at each density, then the scan sampled exactly on the coarser grids (the band alone)."""
    import numpy as np
    import test_density as d
    import test_lateral as lat

    exact = lat.captif_exact()
    ref = np.repeat(exact, len(d.captif_readings(50)) // len(exact), axis=0)

    def row(label: str, grid: str, got: np.ndarray, against: np.ndarray) -> str:
        diff = got[:, :2] - against
        return (
            f"| {label} | {grid} | "
            f"{np.median(diff[:, 0]):+.2f} (vs the exact 8 mm scan) | "
            f"{np.median(diff[:, 1]):+.2f} | {np.median(np.abs(diff[:, 0])):.2f} |"
        )

    rows = []
    for per_cell in (50, 12, 4, 2, 1, 0.5):
        log(f"density: CAPTIF at {per_cell} points per cell against the exact scan")
        got = d.captif_readings(per_cell)
        rows.append(row(f"CAPTIF, {per_cell:g}", _grid(got), got, ref))
    for spec in d.spacing_ladder(d.SPEC)[1:4]:
        log(f"density: the CAPTIF scan exactly on the {spec.spacing * 1e3:.1f} mm grid")
        rows.append(
            row(
                "CAPTIF exact (the band alone)",
                f"{spec.spacing * 1e3:.1f} mm",
                lat.captif_exact(spec),
                exact,
            )
        )
    return rows


def _grid(readings: object) -> str:
    """The grid most of the CAPTIF readings (``test_density.captif_readings``) took: the
    step, and the width of the rows where they were pooled."""
    import numpy as np

    got = np.asarray(readings)
    step, width = float(np.median(got[:, 2])), float(np.median(got[:, 3]))
    pooled = f", rows {width * 1e3:.0f} mm wide" if width > step else ""
    return f"{step * 1e3:.1f} mm{pooled}"


TABLES: dict[str, Callable[[Callable[[str], None]], str]] = {
    "accuracy": accuracy_table,
    "density": density_table,
}
