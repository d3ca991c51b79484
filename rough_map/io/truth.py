"""The world truth file of a simulated traverse: ``world_truth.npz``.

``rough-map simulate`` writes the true world beside the traverse (the traverse's
``height_field``): heights, class map, spacing and origin of a
:class:`~rough_map.types.HeightField`. The heights are int16 steps of at most
:data:`HEIGHT_STEP` with a scale and an offset (``height_scale``, ``height_offset``: z in m
is ``height_offset + height_scale * heights``), or float32 for a wider relief; the class
map (``classes``, int8 indices into ``class_names``; empty without one) is deflated.
Files of older versions with float heights are read too.
"""

from __future__ import annotations

import logging
import zipfile
from pathlib import Path

import numpy as np

from rough_map._files import PathLike, atomic_output
from rough_map.errors import FileFormatError
from rough_map.io.traverse import Traverse
from rough_map.types import HeightField

log = logging.getLogger(__name__)

__all__ = [
    "HEIGHT_STEP",
    "TRUTH_FILE",
    "load_world",
    "save_world",
    "traverse_truth",
]

#: File name of the world truth in a simulated traverse folder.
TRUTH_FILE = "world_truth.npz"

HEIGHT_STEP = 1e-5
"""Coarsest step in m of the stored true heights; a wider relief is stored as float32."""


def save_world(world: HeightField, path: PathLike) -> None:
    """Write a world as .npz (atomic).

    The heights are int16 steps of ``(max - min) / 65534``, at most :data:`HEIGHT_STEP`
    (10 um; 6 um on a random course), with ``height_scale`` and ``height_offset`` in m:
    half the bytes of float32, and far below the 2 mm cells' roughness. A relief over
    0.65 m is stored as float32. The heights are not deflated (at 2 mm they hardly
    compress, by 10 %, and deflating them took longer than simulating the clouds); the
    class map is, to almost nothing.

    Parameters
    ----------
    world : HeightField
        Heights in m, spacing in m, origin in m, optional class map.
    path : str or Path
        Target ``.npz`` file; its folder must exist.
    """
    heights = world.heights
    lo, hi = float(heights.min()), float(heights.max())  # NaN if any height is NaN
    step = (hi - lo) / 65534
    members: dict[str, tuple[np.ndarray, bool]] = {}
    if step <= HEIGHT_STEP:  # False for NaN or inf
        step = step or HEIGHT_STEP
        q = np.empty(heights.shape, dtype=np.int16)
        rows = max(1, 2**21 // max(1, heights.shape[1]))  # row blocks: small temporaries
        for r in range(0, heights.shape[0], rows):
            q[r : r + rows] = np.rint((heights[r : r + rows] - lo) / step) - 32767
        members["heights"] = (q, False)
        members["height_scale"] = (np.asarray(step, dtype=np.float64), False)
        members["height_offset"] = (np.asarray(lo + 32767 * step, dtype=np.float64), False)
    else:
        log.info("world relief %.3f m: true heights stored as float32", hi - lo)
        members["heights"] = (heights.astype(np.float32), False)
    classes = world.classes if world.classes is not None else np.zeros(0)
    members["classes"] = (classes.astype(np.int8), True)
    members["spacing"] = (np.asarray(world.spacing, dtype=np.float64), False)
    members["origin"] = (np.asarray(world.origin, dtype=np.float64), False)
    members["class_names"] = (np.asarray(world.class_names), False)
    _write_npz(Path(path), members)


def _write_npz(path: Path, members: dict[str, tuple[np.ndarray, bool]]) -> None:
    """An .npz archive (atomic) with each member deflated or stored as asked."""
    with atomic_output(path) as tmp, zipfile.ZipFile(tmp, "w", allowZip64=True) as zf:
        for name, (array, deflate) in members.items():
            info = zipfile.ZipInfo(f"{name}.npy")
            info.compress_type = zipfile.ZIP_DEFLATED if deflate else zipfile.ZIP_STORED
            with zf.open(info, "w", force_zip64=True) as fh:
                np.lib.format.write_array(fh, np.asanyarray(array), allow_pickle=False)


def load_world(path: PathLike) -> HeightField:
    """Read a world written by :func:`save_world` (float heights of older files too).

    Raises
    ------
    FileFormatError
        Not such a file (missing, not an .npz, a member missing).
    """
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as d:
            heights = d["heights"].astype(np.float64)
            if "height_scale" in d.files:
                heights *= float(d["height_scale"])
                heights += float(d["height_offset"])
            x0, y0 = (float(v) for v in d["origin"])
            return HeightField(
                heights,
                float(d["spacing"]),
                (x0, y0),
                d["classes"].astype(int) if d["classes"].size else None,
                tuple(str(c) for c in d["class_names"]),
            )
    except (OSError, ValueError, KeyError, AttributeError, zipfile.BadZipFile) as exc:
        raise FileFormatError(path, f"not a rough_map world file: {exc}") from None


def traverse_truth(traverse: Traverse) -> HeightField | None:
    """The true world of a traverse (its ``height_field``, e.g. the simulator's
    ``world_truth.npz``), or None when it names none or the file is not there.

    Raises
    ------
    FileFormatError
        The file is there but is not a world file.
    """
    if traverse.spec.height_field is None:
        return None
    path = traverse.resolve(traverse.spec.height_field)
    return load_world(path) if path.is_file() else None
