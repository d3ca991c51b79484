"""From roughness to driving: a vehicle's response to the measured ground, and its top speed.

:mod:`rough_map.vehicle.spec` reads a vehicle file (a quarter-car and its limits; presets
``rover``, ``tractor`` and ``car`` ship in ``configs/``); :mod:`rough_map.vehicle.response`
turns a patch's ``R`` and ``w`` into the ISO 2631-1 weighted rms acceleration, the rms
suspension travel and the rms dynamic tyre load at a speed, and into the highest speed that
keeps every limit (:meth:`SpeedTable.v_max`, also with 95 % confidence from the standard
errors of R and w).
"""

from rough_map.vehicle.response import (
    MIN_WAVENUMBER,
    Z95,
    Response,
    SpeedTable,
    quarter_car_transfer,
    wheelbase_filter,
    wk_polynomials,
    wk_sections,
    wk_weighting,
)
from rough_map.vehicle.spec import PRESETS, G, Limits, QuarterCar, Vehicle, load_vehicle

__all__ = [
    "MIN_WAVENUMBER",
    "PRESETS",
    "Z95",
    "G",
    "Limits",
    "QuarterCar",
    "Response",
    "SpeedTable",
    "Vehicle",
    "load_vehicle",
    "quarter_car_transfer",
    "wheelbase_filter",
    "wk_polynomials",
    "wk_sections",
    "wk_weighting",
]
