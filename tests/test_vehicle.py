"""From roughness to driving (rough_map.vehicle): ISO 2631-1's Wk against the standard's
table, the spectral responses against a time-domain simulation of the same quarter-car
(scipy.signal) driven over profiles synthesised from ISO 8608 classes, v_max monotone in R and
met at v_max, the presets, and one-line errors on bad vehicle files."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import signal

from rough_map.errors import InputError, SchemaError
from rough_map.iso8608 import PHI0
from rough_map.vehicle import (
    MIN_WAVENUMBER,
    PRESETS,
    SpeedTable,
    load_vehicle,
    wk_sections,
    wk_weighting,
)

BAND = (7.0, 100.0)  # rad/m: the fit band the spectral side integrates up to


def test_wk_is_the_standards_weighting() -> None:
    """ISO 2631-1:1997 Table 3 (Wk, x1000): 0.5 Hz 418, 1 Hz 482, 2 Hz 531, 4 Hz 967,
    8 Hz 1036, 16 Hz 768, 31.5 Hz 405, 63 Hz 186."""
    f = [0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 31.5, 63.0]
    table = np.array([0.418, 0.482, 0.531, 0.967, 1.036, 0.768, 0.405, 0.186])
    assert np.allclose(wk_weighting(f), table, rtol=0.01)


def _profile(R: float, w: float, length: float, dx: float, seed: int) -> np.ndarray:
    """Heights every ``dx`` m over ``length`` m (periodic) with one-sided PSD R Ω^w over
    [MIN_WAVENUMBER, BAND[1]]: each line its exact amplitude, at a random phase."""
    n = round(length / dx)
    omega = 2 * math.pi * np.fft.rfftfreq(n, dx)
    d_omega = 2 * math.pi / length
    amp = np.zeros(omega.size)
    inside = (omega >= MIN_WAVENUMBER) & (omega <= BAND[1])
    amp[inside] = np.sqrt(2 * R * omega[inside] ** w * d_omega)
    phase = np.random.default_rng(seed).uniform(0, 2 * math.pi, omega.size)
    return np.fft.irfft(amp * np.exp(1j * phase) * n / 2, n)


def _drive(R: float, speed: float, seed: int) -> tuple[np.ndarray, float]:
    """A periodic profile for a drive at ``speed``, and its step in m: long enough to hold
    30 lines across the body's resonance, 20 samples a period of its shortest wave (the
    simulation's input is linear between samples)."""
    length = max(200.0, 30.0 * speed)
    dx = 2 * math.pi / BAND[1] / 20
    return _profile(R, -2.0, length, dx, seed), dx


def _filter(system: tuple, x: np.ndarray, dt: float) -> np.ndarray:
    """``x`` through a continuous system (state space or transfer function), discretised
    exactly for an input linear between samples (first-order hold)."""
    discrete = signal.cont2discrete(system, dt, method="foh")
    *coefficients, _ = discrete
    zpk = signal.ss2zpk(*coefficients) if len(coefficients) == 4 else signal.tf2zpk(*coefficients)
    return signal.sosfilt(signal.zpk2sos(*zpk), x)


def _simulate(vehicle, z: np.ndarray, dx: float, speed: float) -> tuple[float, float, float]:
    """Weighted rms acceleration, rms suspension travel and rms dynamic load ratio of the
    quarter-car driven over ``z`` at ``speed``, in the time domain: two passes of the
    periodic profile, the second measured (the first lets the start-up die out). With the
    acceleration at the centre, a second corner follows the first in its track, a
    wheelbase behind (the profile delayed exactly, by its Fourier phase), and the body's
    acceleration is the mean of the two."""
    if vehicle.acceleration_at == "centre":
        k = 2 * math.pi * np.fft.rfftfreq(z.size, dx)
        rear = np.fft.irfft(np.fft.rfft(z) * np.exp(-1j * k * vehicle.wheelbase), z.size)
        front = _corner(vehicle, z, dx, speed)
        acc = (front[0] + _corner(vehicle, rear, dx, speed)[0]) / 2
        return _rms(_weighted(acc, dx / speed), z.size), *front[1:]
    acc, travel, load = _corner(vehicle, z, dx, speed)
    n = z.size
    return _rms(_weighted(acc, dx / speed), n), travel, load


def _rms(x: np.ndarray, n: int) -> float:
    return float(np.sqrt(np.mean(x[n:] ** 2)))  # the second pass


def _weighted(acc: np.ndarray, dt: float) -> np.ndarray:
    for section in wk_sections():  # one second-order section at a time: well conditioned
        b, a = section
        acc = _filter((np.trim_zeros(b, "f"), a), acc, dt)
    return acc


def _corner(vehicle, z: np.ndarray, dx: float, speed: float) -> tuple[np.ndarray, float, float]:
    """One corner over ``z``: its body acceleration over both passes, its rms suspension
    travel and rms dynamic load ratio over the second."""
    q = vehicle.quarter_car
    ms, mu = q.sprung_mass, q.unsprung_mass
    ks, cs, kt = q.suspension_stiffness, q.suspension_damping, q.tyre_stiffness
    # states zs, zs', zu, zu'; input zr
    A = np.array(
        [
            [0, 1, 0, 0],
            [-ks / ms, -cs / ms, ks / ms, cs / ms],
            [0, 0, 0, 1],
            [ks / mu, cs / mu, -(ks + kt) / mu, -cs / mu],
        ]
    )
    B = np.array([[0.0], [0.0], [0.0], [kt / mu]])
    outputs = {  # zs'', zs - zu, kt (zr - zu)
        "acc": (A[1:2], [[0.0]]),
        "travel": ([[1.0, 0, -1, 0]], [[0.0]]),
        "load": ([[0, 0, -kt, 0.0]], [[kt]]),
    }
    dt = dx / speed
    road = np.tile(z, 2)
    y = {
        k: _filter((A, B, np.array(c, float), np.array(d, float)), road, dt)
        for k, (c, d) in outputs.items()
    }
    return y["acc"], _rms(y["travel"], z.size), _rms(y["load"], z.size) / q.static_load


@pytest.mark.parametrize(
    ("preset", "speeds"),
    [("car", (5.0, 15.0, 30.0)), ("tractor", (2.0, 5.0, 10.0)), ("rover", (0.5, 1.0, 2.0))],
)
def test_the_spectral_response_is_the_time_domain_one(preset: str, speeds: tuple) -> None:
    """Within 2 % for classes B, D and F at three speeds, every preset (measured: 0.04 %
    car, 0.14 % tractor, 1.2 % rover)."""
    vehicle = load_vehicle(preset)
    table = SpeedTable(vehicle, BAND)
    for k, cls in enumerate("BDF"):
        R = PHI0[cls]
        for speed in speeds:
            z, dx = _drive(R, speed, seed=k)
            spectral = table.response(R, -2.0, speed)
            timed = _simulate(vehicle, z, dx, speed)
            expected = (
                spectral.weighted_acceleration[0],
                spectral.suspension_travel[0],
                spectral.dynamic_load_ratio[0],
            )
            for name, a, b in zip(("acc", "travel", "load"), timed, expected, strict=True):
                assert a == pytest.approx(b, rel=0.02), (preset, cls, speed, name)


def _at_centre(preset: str):
    return load_vehicle(preset).model_copy(update={"acceleration_at": "centre"})


@pytest.mark.parametrize(
    ("preset", "speeds"), [("car", (5.0, 15.0, 30.0)), ("tractor", (1.0, 4.0, 10.0))]
)
def test_the_wheelbase_filter_is_the_time_domain_two_corners(preset: str, speeds) -> None:
    """The weighted acceleration at the middle of the wheelbase, the rear corner on the
    front's profile a wheelbase later, within 2 % of the time domain for classes B, D, F at
    three speeds; below the corner's alone, and the travel and load those of a corner."""
    vehicle = _at_centre(preset)
    table, corner = SpeedTable(vehicle, BAND), SpeedTable(load_vehicle(preset), BAND)
    for k, cls in enumerate("BDF"):
        R = PHI0[cls]
        for speed in speeds:
            z, dx = _drive(R, speed, seed=10 + k)
            spectral = table.response(R, -2.0, speed)
            acc, travel, load = _simulate(vehicle, z, dx, speed)
            assert acc == pytest.approx(spectral.weighted_acceleration[0], rel=0.02)
            assert travel == pytest.approx(spectral.suspension_travel[0], rel=0.02)
            assert load == pytest.approx(spectral.dynamic_load_ratio[0], rel=0.02)
            alone = corner.response(R, -2.0, speed)
            assert spectral.weighted_acceleration[0] < alone.weighted_acceleration[0]
            assert spectral.dynamic_load_ratio[0] == alone.dynamic_load_ratio[0]


def test_the_centre_needs_a_wheelbase() -> None:
    data = load_vehicle("car").model_dump()
    data.update(acceleration_at="centre", wheelbase=None)
    with pytest.raises(ValueError, match="'centre' needs the wheelbase"):
        type(load_vehicle("car")).model_validate(data)


@pytest.mark.parametrize(
    ("preset", "cls", "centre"),
    [("tractor", "E", False), ("car", "D", False), ("rover", "D", False), ("car", "D", True)],
)
def test_a_drive_at_v_max_meets_the_limit(preset: str, cls: str, centre: bool) -> None:
    """On ground of one constant class, the vehicle at v_max meets its binding limit
    within 5 % in the time domain (also with the acceleration at the wheelbase's centre)."""
    vehicle = _at_centre(preset) if centre else load_vehicle(preset)
    table = SpeedTable(vehicle, BAND)
    R = PHI0[cls]
    v = float(table.v_max(R, -2.0)[0])
    assert 0 < v < vehicle.limits.top_speed
    z, dx = _drive(R, v, seed=7)
    acc, _, load = _simulate(vehicle, z, dx, v)
    ratios = [acc / vehicle.limits.weighted_acceleration, load / vehicle.limits.dynamic_load_ratio]
    assert max(ratios) == pytest.approx(1.0, abs=0.05)


@settings(max_examples=25, deadline=None)
@given(
    lnR=st.floats(math.log(1e-8), math.log(1e-2)),
    factor=st.floats(1.01, 100.0),
    w=st.floats(-3.5, -1.0),
    preset=st.sampled_from(PRESETS),
)
def test_v_max_falls_as_the_ground_gets_rougher(lnR: float, factor: float, w: float, preset: str):
    table = SpeedTable(load_vehicle(preset), BAND)
    R = math.exp(lnR)
    smooth, rough = table.v_max([R, R * factor], [w, w])
    assert rough <= smooth
    # and the speed held with 95 % confidence is never above the estimate's
    sure = table.v_max([R], [w], se_lnR=[0.3], se_w=[0.1])[0]
    assert sure <= smooth


def test_v_max_is_the_top_speed_on_smooth_ground_and_nan_without_a_reading() -> None:
    vehicle = load_vehicle("car")
    table = SpeedTable(vehicle, BAND)
    v = table.v_max([1e-12, math.nan, 1e-4], [-2.0, -2.0, math.nan])
    assert v[0] == vehicle.limits.top_speed and np.isnan(v[1:]).all()


def test_the_band_and_resonances_outside_it_are_said() -> None:
    table = SpeedTable(load_vehicle("car"), BAND)
    slow = table.response(1e-6, -2.0, 1.0)  # 7-100 rad/m at 1 m/s: 1.1-15.9 Hz
    assert slow.band_hz == pytest.approx((7 / (2 * math.pi), 100 / (2 * math.pi)))
    assert slow.outside == []  # body 1.2 Hz and wheel 11.3 Hz inside
    fast = table.response(1e-6, -2.0, 30.0)  # from 33 Hz: both modes below the band
    assert fast.outside == ["body", "wheel"]


def test_presets_state_their_sources() -> None:
    for name in PRESETS:
        vehicle = load_vehicle(name)
        assert vehicle.name == name and len(vehicle.source) > 40
        assert 0.5 < vehicle.quarter_car.body_frequency < 3.0


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (
            {"quarter_car": {"sprung_mass": -250.0}},
            r"quarter_car\.sprung_mass: Input should be greater than 0",
        ),
        ({"quarter_car": {"tyre_stiffness": None}}, r"quarter_car\.tyre_stiffness"),
        ({"limits": {"top_speed": 130.0 / 3.6 * 100}}, r"limits\.top_speed"),
        (
            {"quarter_car": {"suspension_stiffness": 16.0, "tyre_stiffness": 160.0}},
            "body bounces at",
        ),
        ({"quarter_car": {"unsprung_mass": 5000.0}}, "wheel hops at"),
        ({"limits": {"weighted_acceleration": None, "dynamic_load_ratio": None}}, "give weighted"),
        ({"colour": "red"}, r"colour: unknown field"),
    ],
)
def test_bad_vehicle_files_get_one_line(tmp_path: Path, change: dict, message: str) -> None:
    import yaml

    from rough_map.resources import config_file

    data = yaml.safe_load(config_file("vehicle_car.yaml").read_text())
    for key, value in change.items():
        if isinstance(value, dict):
            for k, v in value.items():
                if v is None:
                    data[key].pop(k)
                else:
                    data[key][k] = v
        else:
            data[key] = value
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(SchemaError, match=message) as err:
        load_vehicle(path)
    assert "\n" not in str(err.value) and "bad.yaml" in str(err.value)


def test_an_unknown_vehicle_is_named() -> None:
    with pytest.raises(InputError, match="neither a vehicle file nor a preset"):
        load_vehicle("hovercraft")


@pytest.mark.parametrize(
    ("preset", "speeds", "low"),
    [("car", (10.0, 20.0, 30.0), 0.75), ("tractor", (3.0, 6.0, 10.0), 0.6)],
)
def test_on_a_real_road_profile_the_power_law_reads_the_response_a_little_low(
    preset: str, speeds: tuple, low: float
) -> None:
    """Real material: the measured pavement of tests/data/road_profile_1.txt (544 m every
    0.25 m, ISO class A-B). Its fit R, w (eight 68 m profiles, band 0.09-12.6 rad/m)
    against a time-domain drive over the profile itself (linear between samples, mirrored
    to be periodic): the spectral answer is low, most at low speed where the response
    rests on the shortest waves and the fit's extrapolation (measured: car 0.81-0.97 of
    the drive, tractor 0.67-0.85), because this road is not a power law."""
    from rough_map.psd import patch_roughness

    d = np.loadtxt(Path(__file__).parent / "data" / "road_profile_1.txt")
    x, z = d[:, 0] - d[0, 0], d[:, 1]
    z = z - np.polyval(np.polyfit(x, z, 1), x)
    fit = patch_roughness(z[:2176].reshape(8, 272), 0.25)
    table = SpeedTable(load_vehicle(preset), (2 * math.pi / 68.0, math.pi / 0.25))
    dx = 0.025
    fine = np.interp(np.arange(0.0, x[-1], dx), x, z)
    road = np.concatenate([fine, fine[::-1]])
    ratios = []
    for speed in speeds:
        acc, _, load = _simulate(load_vehicle(preset), road, dx, speed)
        spectral = table.response(fit.R, fit.w, speed)
        ratios += [spectral.weighted_acceleration[0] / acc, spectral.dynamic_load_ratio[0] / load]
    assert low < min(ratios) and max(ratios) < 1.05, ratios
    assert ratios[-2] > 0.8  # at the highest speed, the acceleration within 20 %
