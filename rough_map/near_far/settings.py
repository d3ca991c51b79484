"""Near-to-far settings of the map commands: ``configs/near_far.yaml`` and the command line.

Read by :func:`load_near_far_settings`; ``rough-map map``/``report``/``batch`` take the file
with ``--near-far-config`` and override single values with ``--far-tile``, ``--far-range``,
``--far-weight`` and ``--far-confidence``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from rough_map.config import StereoCalibration, load_model
from rough_map.near_far.cells import NearField
from rough_map.patch import Extraction, PatchSpec
from rough_map.resources import config_file

__all__ = ["CONFIG_FILE", "NearFarSettings", "load_near_far_settings"]

#: The shipped config file.
CONFIG_FILE = "near_far.yaml"


class NearFarSettings(BaseModel):
    """The file ``configs/near_far.yaml``.

    Attributes
    ----------
    tile_size_m : float
        Side of the square image tiles, m, measured on the ground at the centre of the
        near-field patch (converted to px with the calibration, :meth:`tile_px`).
    max_range_m : float
        Farthest far-field cell from the vehicle, m.
    weight : float
        Weight of one far-field prediction in the map, relative to a near-field patch.
    min_confidence : float
        Calibrated probability a far cell needs to be labelled; below it the model (and
        the map's ``far_class``) abstains.
    settle_frames : int
        Frames on either side of a learnt frame that must carry its class and no defect.
    min_posterior : float
        Lowest path-filter probability of a learnt frame's class.
    recall_min_confidence : float
        Calibrated probability a remembered cell needs to be recalled.
    calibrate : bool
        Calibrate the confidence on predictions the near field checked later, and abstain
        until far predictions of two classes were checked
        (:mod:`rough_map.near_far.calibration`); false trusts the looks' own
        probabilities (a few frames of a short traverse are not enough to check them).
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    tile_size_m: float = Field(0.05, ge=1e-3, le=10)
    max_range_m: float = Field(8.0, gt=0, le=1000)
    weight: float = Field(0.3, gt=0)
    min_confidence: float = Field(0.8, ge=0, le=1)
    settle_frames: int = Field(3, ge=0, le=100_000)
    min_posterior: float = Field(0.8, ge=0, le=1)
    recall_min_confidence: float = Field(0.9, ge=0, le=1)
    calibrate: bool = True

    def tile_px(self, calib: StereoCalibration, patch: PatchSpec | Extraction) -> int:
        """``tile_size_m`` in px of ``calib``'s left image at the centre of the patch (at
        least 4)."""
        near = NearField.of(patch)
        centre = np.array([np.mean(near.ahead), np.mean(near.lateral), 0.0])
        camera = np.asarray(calib.camera_to_vehicle, dtype=float)[:3, 3]
        distance = float(np.linalg.norm(centre - camera))
        return max(4, round(self.tile_size_m * math.sqrt(calib.fx * calib.fy) / distance))


def load_near_far_settings(path: str | Path | None = None) -> NearFarSettings:
    """The settings of a config file (default the shipped ``configs/near_far.yaml``).

    Raises
    ------
    FileFormatError, SchemaError
        Unreadable file, or content that does not follow :class:`NearFarSettings`.
    """
    settings: NearFarSettings = load_model(
        path if path is not None else config_file(CONFIG_FILE), NearFarSettings
    )
    return settings
