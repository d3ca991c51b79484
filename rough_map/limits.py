"""The limits every reader checks a file against before it allocates: one table of data.

A file from elsewhere declares sizes, counts and nesting; each reader compares them with the
file's real size and with a value of :data:`LIMITS` before it allocates anything, and
refuses the file with a one-line :class:`~rough_map.errors.RoughMapError` beyond it. The
values live here and nowhere else, each with its unit and what it bounds, in the manner of
rasterio's profiles; the README's *Limits* table is :func:`markdown_table` (a test
compares them).

Units: ``B`` bytes, ``px`` pixels, ``points``, ``characters``, ``samples``, ``cells``;
``x`` a ratio; ``""`` a count of the things named.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

__all__ = ["LIMITS", "Limits", "markdown_table"]


def _limit(value: int, unit: str, what: str) -> Any:
    """A field of :class:`Limits`: its value is the default, its unit and what it bounds
    the field's metadata."""
    return field(default=value, metadata={"unit": unit, "what": what})


@dataclass(frozen=True)
class Limits:
    """The values of every boundary check (see the module's text).

    Where the values come from: a real ROS 2 ``metadata.yaml`` holds about 1 kB per topic
    and ruamel parses it at about 6 s of CPU per MB; rosbag writers use chunks of 768 KiB to
    4 MiB; a forest of 200 trees is a model file of a few MB with a ``schema.json`` of about
    6 MB and a nesting of about 40; real airborne lidar compresses about 6 times in LAZ (a
    rough simulated grid 25); the estimator's correlation between profiles takes about
    200 MB and several seconds at 512 samples a side, its per-profile tables about 250 MB
    at 4096 samples, and 2**24 cells are 128 MB of float64.
    """

    points: int = _limit(
        2_000_000_000,
        "points",
        "points declared by any cloud header (and never more than its bytes hold)",
    )
    cloud_header: int = _limit(65_536, "B", "PLY / PCD header")
    npy_header: int = _limit(10_000, "B", "`.npy` header (NumPy's own default)")
    laz_ratio: int = _limit(200, "x", "LAZ: decoded point bytes per byte of point data")
    archive_member: int = _limit(4 * 2**30, "B", "`.npz` member, uncompressed")
    deflate_ratio: int = _limit(
        1100,
        "x",
        "uncompressed size of a deflated `.npz` member or image per compressed byte "
        "(deflate's best is 1032)",
    )
    image_pixels: int = _limit(100_000_000, "px", "image (PNG, JPEG, BMP, PNM, TIFF)")
    calibration_image_side: int = _limit(65_536, "px", "image side of a stereo calibration")
    document: int = _limit(
        64 * 2**20, "B", "JSON or YAML file (traverse, configs, calibrations, metadata)"
    )
    yaml_document: int = _limit(
        4 * 2**20, "B", "YAML file (parsed by the safe pure-Python loader: no Python tags)"
    )
    document_depth: int = _limit(64, "", "nesting of JSON and YAML")
    int_digits: int = _limit(30, "", "digits of an integer in JSON and YAML")
    yaml_alias_values: int = _limit(100_000, "", "values YAML aliases may add")
    model_file: int = _limit(256 * 2**20, "B", "model file (`.skops`)")
    model_uncompressed: int = _limit(
        256 * 2**20,
        "B",
        "members of a model file, uncompressed (each time the schema refers to one)",
    )
    model_members: int = _limit(100_000, "", "members of a model file")
    model_member_ratio: int = _limit(
        200, "x", "uncompressed size per compressed byte of a model member above 1 MB"
    )
    model_schema: int = _limit(32 * 2**20, "B", "`schema.json` of a model file")
    model_schema_depth: int = _limit(200, "", "nesting of a model's `schema.json`")
    model_card: int = _limit(16 * 2**20, "B", "model card")
    bag_metadata: int = _limit(256 * 2**10, "B", "ROS 2 `metadata.yaml`")
    bag_metadata_depth: int = _limit(32, "", "bracket nesting in a ROS 2 `metadata.yaml`")
    bag_storage_files: int = _limit(1024, "", "storage files a ROS 2 bag lists")
    bag_topics: int = _limit(10_000, "", "topics a ROS 2 bag's metadata lists")
    bag_name: int = _limit(
        4096, "characters", "a topic, type or file name in a ROS 2 `metadata.yaml`"
    )
    bag_chunk: int = _limit(256 * 2**20, "B", "a bag chunk, decompressed")
    archive_ratio: int = _limit(
        10, "x", "arrays read from a `.npz` archive per byte of it (beyond 4 MiB)"
    )
    raster_cells: int = _limit(
        2**31, "cells", "cells of a truth GeoTIFF (and at most 1100 per byte)"
    )
    raster_class_names: int = _limit(65_536, "", "class names a truth GeoTIFF's sidecar lists")
    model_classes: int = _limit(1000, "", "classes of a model")
    model_features: int = _limit(100_000, "", "features of a model")
    model_bins: int = _limit(100_000, "", "wavenumbers of a model's spectral band")
    patch_samples: int = _limit(
        512, "samples", "samples per side of a patch (the estimator's cost grows as its square)"
    )
    profile_samples: int = _limit(4096, "samples", "samples of one profile given to the estimator")
    grid_cells: int = _limit(2**24, "cells", "cells of a height grid given to `profile_psd`")


#: The values: each field's default.
LIMITS = Limits()


def shown(value: int, unit: str) -> str:
    """``65536, "B"`` -> ``64 KiB``; ``2**24, "cells"`` -> ``16,777,216 cells``."""
    if unit == "B":
        for name, scale in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
            if value >= scale and value % scale == 0:
                return f"{value // scale:,} {name}"
        return f"{value:,} B"
    if unit == "x":
        return f"{value:,}x"
    return f"{value:,} {unit}".rstrip()


def markdown_table() -> str:
    """The README's limits table: what, limit, name in :data:`LIMITS`, one row each."""
    rows = ["| what | limit | `LIMITS.` |", "|---|---|---|"]
    for f in dataclasses.fields(Limits):
        value = getattr(LIMITS, f.name)
        rows.append(f"| {f.metadata['what']} | {shown(value, f.metadata['unit'])} | `{f.name}` |")
    return "\n".join(rows)
