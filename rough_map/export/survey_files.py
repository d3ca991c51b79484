"""Writing a roughness raster (:func:`rough_map.survey.roughness_raster`): GeoTIFFs, a
CSV and PNGs, as one set."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from rough_map._files import PathLike, output_set
from rough_map.export.geotiff import write_class_geotiff, write_values_geotiff
from rough_map.export.png import write_pngs
from rough_map.map.grid import GridMap

__all__ = ["SURVEY_OUTPUTS", "write_roughness_raster"]

#: What :func:`write_roughness_raster` writes in its folder (replaced as a set).
SURVEY_OUTPUTS = ("roughness.tif", "roughness_class.*", "roughness.csv", "roughness_*.png")


def write_roughness_raster(
    grid: GridMap,
    out_dir: PathLike,
    *,
    png: bool = True,
    progress: bool = False,
    crs: Any = None,
) -> dict[str, Path]:
    """Write a roughness raster as one set in ``out_dir`` (your other files there kept):
    ``roughness.tif`` (a float32 band per value layer, nodata where no window was read),
    ``roughness_class.tif`` (uint8 ISO 8608 class with a colour table, nodata 255),
    ``roughness.csv`` (one row per window read: centre x, y in m and every value) and, with
    ``png``, ``roughness_<layer>.png`` with legends.

    ``crs``: the files' CRS where rough_map's cannot name the raster's
    (:attr:`rough_map.io.raster.HeightRaster.file_crs`).

    Returns
    -------
    dict of str to Path
        What was written, by kind (``values``, ``class``, ``csv``, and one per PNG).
    """
    out = Path(out_dir)
    values = [n for n in grid.layers if grid.info(n).kind == "value"]
    written: dict[str, Path] = {}
    with output_set(out, owned=SURVEY_OUTPUTS) as stage:
        write_values_geotiff(grid, stage / "roughness.tif", layers=values, crs=crs)
        write_class_geotiff(grid, stage / "roughness_class.tif", layer="iso_class", crs=crs)
        _write_csv(grid, stage / "roughness.csv", values)
        pngs = write_pngs(grid, stage, "roughness", progress=progress) if png else {}
    written.update(values=out / "roughness.tif", csv=out / "roughness.csv")
    written["class"] = out / "roughness_class.tif"
    written.update({f"png_{k}": out / v.name for k, v in pngs.items()})
    return written


def _write_csv(grid: GridMap, path: Path, values: list[str]) -> None:
    """One row per window read: its centre (m) and its values."""
    rows, cols = np.nonzero(grid["valid"] > 0)
    x, y = grid.geometry.cell_center(rows, cols)
    classes = np.asarray(grid.info("iso_class").categories, dtype=object)
    columns = [np.char.mod("%.3f", x), np.char.mod("%.3f", y)]
    columns += [np.char.mod("%.6g", grid[n][rows, cols]) for n in values]
    columns.append(classes[grid["iso_class"][rows, cols].astype(int)])
    with path.open("w", encoding="utf-8", newline="") as fh:
        fh.write(",".join(["x", "y", *values, "iso_class"]) + "\n")
        fh.writelines(",".join(cells) + "\n" for cells in zip(*columns, strict=True))
