"""The tables the package ships, ``rough_map/data/leakage_tables.npz``: the leakage tables
(:mod:`rough_map.psd._leakage`) and the lateral tables of cell means
(:mod:`rough_map.psd._lateral`) of common profile lengths. Both modules read the file; this
one writes it (it needs both, and ``_lateral`` reads ``_leakage``)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rough_map._files import atomic_output
from rough_map.errors import InputError
from rough_map.limits import LIMITS
from rough_map.patch._params import check_int
from rough_map.psd._lateral import compute_lateral_tables
from rough_map.psd._leakage import GRIDDINGS, SHIPPED_TABLES, compute_leakage_table


def write_leakage_tables(
    path: Path = SHIPPED_TABLES, sizes: Sequence[int] = (40, 56, 64, 80, 100, 112, 128, 225)
) -> None:
    """Precompute the leakage tables of the Hann window for common profile lengths, and
    the lateral tables of cell means (:mod:`rough_map.psd._lateral`).

    The package ships them (``rough_map/data/leakage_tables.npz``) so that a one-shot
    command does not spend ~50 ms building one; a test checks they are up to date.

    Parameters
    ----------
    path : Path
        The ``.npz`` to write.
    sizes : sequence of int
        Profile lengths in samples.
    """
    if not isinstance(path, str | Path):
        raise InputError(f"path must be a file path; got {type(path).__name__}")
    path = Path(path)
    if isinstance(sizes, str | bytes) or not isinstance(sizes, Sequence) or len(sizes) > 64:
        raise InputError("sizes must be a sequence of at most 64 profile lengths (samples)")
    for n in sizes:
        check_int("sizes[i]", n, low=8, high=LIMITS.patch_samples, unit="samples")
    sizes = [int(n) for n in sizes]
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise InputError(f"{path.parent}: cannot create the folder ({err.strerror})") from None
    tables: dict[str, Any] = {
        f"hann_{n}_{g}": compute_leakage_table(n, "hann", g) for n in sizes for g in GRIDDINGS
    }
    for n in sizes:
        tables[f"lateral_ratio_{n}"], tables[f"lateral_coherence_{n}"] = compute_lateral_tables(n)
    with atomic_output(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **tables)
