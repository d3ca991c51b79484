"""Vehicle files: a quarter-car and the limits that matter to it, as YAML (or JSON).

A vehicle file names the model (a quarter-car: one corner's sprung and unsprung mass, its
suspension spring and damper, its tyre's vertical stiffness; optionally a wheelbase, the rear
corner following the front in its track) and the limits a drive must
keep: the ISO 2631-1 frequency-weighted rms vertical acceleration of the body (comfort,
payload or sensors), the rms dynamic tyre load over the static load (road holding) and a top
speed. It is validated like every other config (:func:`rough_map.config.load_model`): a bad
file (a negative mass, a missing field, a stiffness in the wrong unit) is a one-line
:class:`~rough_map.errors.SchemaError` naming the field.

Three presets ship in ``configs/`` (``vehicle_rover.yaml``, ``vehicle_tractor.yaml``,
``vehicle_car.yaml``), each stating its sources; :func:`load_vehicle` takes a preset's name or
a file.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from rough_map.config import load_model
from rough_map.errors import InputError
from rough_map.resources import config_file

__all__ = ["PRESETS", "G", "Limits", "QuarterCar", "Vehicle", "load_vehicle"]

#: Standard gravity, m/s².
G = 9.80665
#: The vehicles rough_map ships (``configs/vehicle_NAME.yaml``).
PRESETS = ("rover", "tractor", "car")


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class QuarterCar(_Model):
    """One corner of the vehicle: body and wheel masses, suspension, tyre (SI units)."""

    sprung_mass: float = Field(gt=0, le=1e5, description="Body mass on this wheel, kg.")
    unsprung_mass: float = Field(gt=0, le=1e4, description="Wheel, axle share, brake, kg.")
    suspension_stiffness: float = Field(gt=0, le=1e8, description="Spring rate, N/m.")
    suspension_damping: float = Field(gt=0, le=1e7, description="Damper rate, N·s/m.")
    tyre_stiffness: float = Field(gt=0, le=1e9, description="Tyre vertical stiffness, N/m.")

    @model_validator(mode="after")
    def _plausible(self) -> QuarterCar:
        # a body mode between 0.2 and 20 Hz and a wheel mode above it: catches kN/m given
        # for N/m, grams for kilograms and the masses swapped
        body, wheel = self.body_frequency, self.wheel_frequency
        if not 0.2 <= body <= 20.0:
            raise ValueError(
                f"the body bounces at {body:.3g} Hz (expected 0.2-20 Hz): are the masses in kg "
                "and the stiffnesses in N/m?"
            )
        if not wheel > body:
            raise ValueError(
                f"the wheel hops at {wheel:.3g} Hz, below the body's {body:.3g} Hz: is the "
                "unsprung mass larger than the sprung one?"
            )
        return self

    @property
    def body_frequency(self) -> float:
        """Undamped body (bounce) frequency in Hz: the spring and tyre in series."""
        k = self.suspension_stiffness * self.tyre_stiffness
        k /= self.suspension_stiffness + self.tyre_stiffness
        return math.sqrt(k / self.sprung_mass) / (2 * math.pi)

    @property
    def wheel_frequency(self) -> float:
        """Undamped wheel-hop frequency in Hz: the wheel between spring and tyre."""
        k = self.suspension_stiffness + self.tyre_stiffness
        return math.sqrt(k / self.unsprung_mass) / (2 * math.pi)

    @property
    def static_load(self) -> float:
        """Static tyre load in N."""
        return (self.sprung_mass + self.unsprung_mass) * G


class Limits(_Model):
    """What a drive must keep (each optional but the top speed)."""

    weighted_acceleration: float | None = Field(
        None,
        gt=0,
        le=100,
        description="Highest ISO 2631-1 Wk-weighted rms vertical acceleration of the body, m/s².",
    )
    dynamic_load_ratio: float | None = Field(
        None,
        gt=0,
        le=1,
        description="Highest rms dynamic tyre load over the static load (road holding), 1.",
    )
    top_speed: float = Field(gt=0, le=150, description="Top speed, m/s.")


class Vehicle(_Model):
    """Content of a vehicle file."""

    model_config = ConfigDict(title="Vehicle")

    schema_version: str = Field("1.0", pattern=r"^1\.0$", description="Version of this format.")
    name: str = Field(min_length=1, description="Name of the vehicle.")
    source: str = Field(min_length=1, description="Where the numbers come from.")
    quarter_car: QuarterCar
    wheelbase: float | None = Field(
        None,
        gt=0,
        le=50,
        description=(
            "Wheelbase in m: front and rear wheels run in one track, the rear wheelbase/v "
            "later. It enters the weighted acceleration taken at the centre "
            "(acceleration_at)."
        ),
    )
    acceleration_at: Literal["wheel", "centre"] = Field(
        "wheel",
        description=(
            "Where the weighted acceleration is taken: 'wheel', over one wheel (the "
            "quarter-car), or 'centre', midway along the wheelbase, the mean of the front "
            "and rear corners' body accelerations (the bounce of a body whose pitch inertia "
            "decouples its axles, dynamic index 1); 'centre' needs the wheelbase."
        ),
    )
    limits: Limits

    @model_validator(mode="after")
    def _some_limit(self) -> Vehicle:
        if self.limits.weighted_acceleration is None and self.limits.dynamic_load_ratio is None:
            raise ValueError("limits: give weighted_acceleration and/or dynamic_load_ratio")
        if self.acceleration_at == "centre" and self.wheelbase is None:
            raise ValueError("acceleration_at: 'centre' needs the wheelbase (m)")
        return self


def load_vehicle(name_or_path: str | Path) -> Vehicle:
    """A preset by name (:data:`PRESETS`) or a vehicle file.

    Raises
    ------
    FileFormatError, SchemaError
        An unreadable file, or content that does not follow :class:`Vehicle`.
    InputError
        Neither a preset nor an existing file.
    """
    text = str(name_or_path)
    if text in PRESETS:
        return load_model(config_file(f"vehicle_{text}.yaml"), Vehicle)
    path = Path(name_or_path)
    if not path.exists():
        raise InputError(
            f"{text!r:.80} is neither a vehicle file nor a preset ({', '.join(PRESETS)})"
        )
    return load_model(path, Vehicle)
