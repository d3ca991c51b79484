"""Speed advice per frame: the highest speed a vehicle keeps its limits at over each patch.

:func:`speed_advice` adds to a features table, from each valid frame's ``R`` and ``w``
(the fit over the table's band, ``omega``) and a vehicle
(:class:`rough_map.vehicle.Vehicle`): ``v_max`` (m/s), ``v_max_95`` (m/s, the speed that
holds with 95 % confidence from ``se_lnR`` and ``se_w``) and, at a chosen speed, the
responses ``weighted_acceleration`` (m/s², ISO 2631-1 Wk), ``suspension_travel`` (m) and
``dynamic_load_ratio`` (1), all rms. Invalid frames read NaN.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from rough_map.errors import InputError
from rough_map.features.table import FeatureTable
from rough_map.vehicle import SpeedTable, Vehicle

__all__ = ["speed_advice", "speed_table"]


def speed_table(table: FeatureTable, vehicle: Vehicle) -> SpeedTable:
    """The vehicle's :class:`~rough_map.vehicle.SpeedTable` over the table's band."""
    omega = np.asarray(table.omega, dtype=float)
    if omega.size < 2:
        raise InputError(f"{table.name}: the table has no spectrum band to drive over")
    return SpeedTable(vehicle, (float(omega[0]), float(omega[-1])))


def speed_advice(table: FeatureTable, vehicle: Vehicle, speed: float | None = None) -> FeatureTable:
    """``table`` with the speed advice columns filled (see the module docstring).

    Parameters
    ----------
    table : FeatureTable
        Features of a traverse.
    vehicle : Vehicle
        The model and its limits.
    speed : float, optional
        A speed in m/s (up to the vehicle's top speed) for the response columns.
    """
    speeds = speed_table(table, vehicle)
    valid = table.valid
    R = np.where(valid, table["R"], np.nan)
    w = np.where(valid, table["w"], np.nan)
    columns: dict[str, Any] = {
        "v_max": speeds.v_max(R, w),
        "v_max_95": speeds.v_max(R, w, se_lnR=table["se_lnR"], se_w=table["se_w"]),
    }
    if speed is not None:
        response = speeds.response(R, w, speed)
        columns.update(
            weighted_acceleration=response.weighted_acceleration,
            suspension_travel=response.suspension_travel,
            dynamic_load_ratio=response.dynamic_load_ratio,
        )
    return table.replace(**columns)
