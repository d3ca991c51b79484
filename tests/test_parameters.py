"""Public parameters of the patch, PSD and features entry points: every bad value is a
one-line InputError naming the parameter, up front, and hostile sizes stay within budget."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from fuzzing import FUZZ, assert_bounded
from hypothesis import given
from hypothesis import strategies as st

from rough_map import psd
from rough_map.errors import InputError, PatchError
from rough_map.features import cloud_roughness, frame_features
from rough_map.patch import (
    Extraction,
    PatchSpec,
    auto_spacing,
    check_points,
    compensate_tilt,
    grid_points,
    points_in_patch,
    spacing_ladder,
)

B = 0.008
RNG = np.random.default_rng(0)
HEIGHTS = np.cumsum(RNG.normal(0, 1e-3, (6, 64)), axis=1)
SMALL = PatchSpec(size=0.256, spacing=0.016)  # 16 x 16 cells
CLOUD = np.column_stack(
    [RNG.uniform(0.85, 1.15, 3000), RNG.uniform(-0.15, 0.15, 3000), RNG.normal(0, 2e-3, 3000)]
)

# ----------------------------------------------------------------------------- PSD


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"window": "x"}, "window must be a scipy window name such as hann"),
        ({"window": ("tukey", 0.5)}, "window must be"),
        ({"window": None}, "window must be"),
        ({"method": "x"}, "method must be one of unbiased, paper; got 'x'"),
        ({"method": np.array(["unbiased"])}, "method must be one of"),
        ({"gridding": 3}, "gridding must be one of"),
        ({"noise_psd": "x"}, r"noise_psd must be a finite number in m\^3/rad"),
        ({"noise_psd": -1.0}, "noise_psd"),
        ({"max_gap": math.nan}, "max_gap must be a finite number in m"),
        ({"max_gap": "0.05"}, "max_gap"),
        ({"max_gap_fraction": 1.5}, r"max_gap_fraction must be a finite number in \[0, 1\]"),
        ({"waviness": "x"}, "waviness must be a negative number"),
        ({"waviness": math.inf}, "waviness"),
        ({"omega0": 0.0}, "omega0 must be a finite number in rad/m"),
        ({"omega0": True}, "omega0"),
        ({"nperseg": 4}, r"nperseg must be an integer \(samples\) in \[8,"),
        ({"nperseg": 16.5}, "nperseg"),
        ({"noverlap": -1}, "noverlap"),
        ({"min_profiles": 0}, r"min_profiles must be an integer \(profiles\)"),
        ({"min_profiles": 2**70}, "min_profiles"),
        ({"subtract_noise": "yes"}, "subtract_noise must be true or false"),
    ],
)
def test_bad_estimator_options(kwargs: dict[str, Any], match: str) -> None:
    with pytest.raises(InputError, match=match):
        psd.patch_roughness(HEIGHTS, B, **kwargs)
    with pytest.raises(InputError, match=match):
        psd.patch_roughness_batch(HEIGHTS[None], B, **kwargs)


@pytest.mark.parametrize(
    ("spacing", "match"),
    [
        ("0.008", "spacing must be a positive length in m"),
        (True, "spacing"),
        (1e9, r"spacing .* \(at most 1000\)"),
        ([0.008], "spacing"),
    ],
)
def test_bad_spacing(spacing: Any, match: str) -> None:
    with pytest.raises(InputError, match=match):
        psd.patch_roughness(HEIGHTS, spacing)
    with pytest.raises(InputError, match=match):
        psd.profile_psd(HEIGHTS, spacing)
    with pytest.raises(InputError, match=match):
        psd.fill_gaps(HEIGHTS, spacing)


@pytest.mark.parametrize(
    ("heights", "match"),
    [
        (np.zeros((3, 1_000_000)), "1000000 samples per profile; the estimator takes at most 4096"),
        (np.zeros((3, 1000)), "at most 512 per segment when it correlates profiles"),
        (np.zeros((1, 64)), "need at least 3"),
        (np.ones((6, 64), dtype=complex), "real numeric array"),
        (np.array([[object()] * 64] * 6), "real numeric array"),
        (np.full((6, 64), -np.inf), "infinite"),
        # found by tools/fuzz_all.py: a ragged list (numpy's ValueError), and heights of
        # 1e308 m whose spectra overflowed into a NaN waviness (an IndexError)
        ([[1.0] * 64, [1.0] * 63], "real numeric array"),
        (np.full((6, 64), 1e308), r"heights reach 1e\+308 m, beyond 1e\+06 m: wrong units"),
    ],
)
def test_hostile_height_grids(heights: np.ndarray, match: str) -> None:
    with pytest.raises(InputError, match=match):
        psd.patch_roughness(heights, B)
    with pytest.raises(InputError, match=match):
        psd.patch_roughness_batch([heights, heights] if isinstance(heights, list) else
                                  np.stack([heights, heights]), B)  # fmt: skip


def test_spectrum_budget() -> None:
    with pytest.raises(InputError, match=r"heights has 16777218 cells .*; at most 16777216"):
        psd.profile_psd(np.broadcast_to(np.float64(0.0), (2, 2**23 + 1)), B)
    omega, p = psd.profile_psd(np.zeros((3, 100_000)), B)  # a long profile: only a spectrum
    assert p.shape == (3, omega.size)


def test_bad_profile_psd_and_fill_gaps_options() -> None:
    with pytest.raises(InputError, match="window must be"):
        psd.profile_psd(HEIGHTS, B, window="x")
    with pytest.raises(InputError, match="nperseg"):
        psd.profile_psd(HEIGHTS, B, nperseg="16")
    with pytest.raises(InputError, match="max_gap_fraction"):
        psd.fill_gaps(HEIGHTS, B, max_gap_fraction=-0.1)
    with pytest.raises(InputError, match="2-D grid"):
        psd.fill_gaps(HEIGHTS[0], B)


def test_bad_log_bias_arguments() -> None:
    with pytest.raises(InputError, match="window"):
        psd.log_bias([1], 16, 8, 64)
    with pytest.raises(InputError, match=r"noverlap must be an integer \(samples\) in \[0, 15\]"):
        psd.log_bias("hann", 16, 16, 64)
    assert psd.log_bias("hann", 64, 0, 64) == pytest.approx(-np.euler_gamma)


def test_unknown_batch_option_is_both_errors() -> None:
    with pytest.raises(InputError, match="windw"):
        psd.patch_roughness_batch(HEIGHTS[None], B, windw="hann")


# ----------------------------------------------------------------------------- patch


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"spacing": 1e-9}, r"8.96e\+08 samples per profile .* at most 512"),
        ({"spacing": 0.0}, r"spacing must be a finite number in m in \(0, 1000\]"),
        ({"spacing": 5e-5}, "17920 samples per profile .* at most 512: use a larger spacing"),
        ({"size": 1e6}, "size"),
        ({"spacing": "x"}, "spacing"),
        ({"size": True}, "size"),
        ({"ahead": math.inf}, "ahead must be a finite number in m"),
        ({"lateral": "0"}, "lateral"),
        ({"ahead": 1e300}, "ahead"),
        ({"ahead": 10**400}, r"ahead must be a finite number in m .*; got 1000000000"),  # no float
    ],
)
def test_bad_patch_specs(kwargs: dict[str, Any], match: str) -> None:
    with pytest.raises(InputError, match=match):
        PatchSpec(**kwargs)


def test_bad_extraction() -> None:
    with pytest.raises(InputError, match="method must be one of unbiased, paper"):
        Extraction(method=["paper"])
    with pytest.raises(InputError, match="unknown extraction settings 1"):
        Extraction.from_dict({1: 2, "size": 0.5})
    with pytest.raises(InputError, match="spacing"):
        Extraction.from_dict({"spacing": np.array([0.008, 0.01])})


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"min_points": -1}, r"min_points must be an integer \(points\)"),
        ({"min_points": 1.5}, "min_points"),
        ({"roll": "x"}, "roll must be a finite number in rad"),
        ({"pitch": math.nan}, "pitch"),
        ({"level": 1}, "level must be true or false"),
        ({"estimate_noise": None}, "estimate_noise"),
        ({"level_threshold": -0.1}, "level_threshold must be a finite number in rad"),
        ({"spec": "x"}, "spec must be a PatchSpec"),
    ],
)
def test_bad_grid_options(kwargs: dict[str, Any], match: str) -> None:
    with pytest.raises(InputError, match=match):
        grid_points(CLOUD, **kwargs)


def test_bad_clouds_and_counts() -> None:
    with pytest.raises(InputError, match="real numeric"):
        check_points(CLOUD.astype(complex))
    with pytest.raises(InputError, match=r"shape \(N, 3\)"):
        points_in_patch(np.zeros((4, 4)), SMALL)
    with pytest.raises(InputError, match="spec must be a PatchSpec"):
        spacing_ladder(None)
    with pytest.raises(InputError, match=r"n_points must be an integer \(points\)"):
        auto_spacing(math.nan, SMALL)
    with pytest.raises(InputError, match="min_points_per_cell must be > 0"):
        auto_spacing(100, SMALL, min_points_per_cell="x")


def test_cloud_with_nan_rows_is_gridded() -> None:
    cloud = CLOUD.copy()
    cloud[::3] = np.nan
    grid = grid_points(cloud, SMALL, min_points=10)
    finite = np.isfinite(cloud).all(axis=1)
    assert grid.n_points == grid_points(cloud[finite], SMALL, min_points=10).n_points > 0


def test_bad_feature_options() -> None:
    with pytest.raises(InputError, match="extraction must be an Extraction"):
        frame_features(CLOUD, "x")
    with pytest.raises(InputError, match=r"min_fill must be a finite number in \[0, 1\]"):
        frame_features(CLOUD, SMALL, min_fill=2.0)
    with pytest.raises(InputError, match="roll"):
        cloud_roughness(CLOUD, SMALL, roll=math.inf)


# ----------------------------------------------------------------------------- hypothesis

HOSTILE = st.sampled_from(
    [
        math.nan,
        math.inf,
        -math.inf,
        -1,
        -1.0,
        0,
        0.0,
        1e-300,
        1e300,
        -1e300,
        2**64,
        10**30,
        2.5,
        "x",
        "0.1",
        "",
        None,
        True,
        False,
        [1.0],
        {},
        b"x",
        np.float64("nan"),
        np.array([1.0, 2.0]),
        np.int64(-5),
        object(),
    ]
)

_PSD_KW = ("window", "method", "nperseg", "noverlap", "omega0", "noise_psd", "subtract_noise",
           "max_gap", "max_gap_fraction", "min_profiles", "gridding", "waviness")  # fmt: skip


def _call(target: str, name: str, value: Any) -> Any:
    if target == "patch_roughness":
        if name == "heights":
            return psd.patch_roughness(value, B)
        if name == "spacing":
            return psd.patch_roughness(HEIGHTS, value)
        return psd.patch_roughness(HEIGHTS, B, **{name: value})
    if target == "profile_psd":
        if name in ("heights", "spacing"):
            args = {"heights": HEIGHTS, "spacing": B, name: value}
            return psd.profile_psd(args["heights"], args["spacing"])
        return psd.profile_psd(HEIGHTS, B, **{name: value})
    if target == "fill_gaps":
        args = {"heights": HEIGHTS, "spacing": B, "max_gap": 0.05, "max_gap_fraction": 0.2}
        args[name] = value
        return psd.fill_gaps(args.pop("heights"), args.pop("spacing"), **args)
    if target == "PatchSpec":
        return PatchSpec(**{name: value})
    if target == "grid_points":
        if name == "points":
            return grid_points(value, SMALL, min_points=10)
        return grid_points(CLOUD, **{"spec": SMALL, name: value})
    if target == "auto_spacing":
        return auto_spacing(**{"n_points": 5000, "spec": SMALL, name: value})
    if target == "frame_features":
        if name == "points":
            return frame_features(value, SMALL, min_points=10)
        return frame_features(CLOUD, **{"extraction": SMALL, name: value})
    if target == "Extraction":
        return Extraction(**{name: value})
    if target == "Extraction.from_dict":
        return Extraction.from_dict({name: value})
    if target == "compensate_tilt":
        args = {"points": CLOUD, "roll": 0.01, "pitch": 0.01, name: value}
        return compensate_tilt(args["points"], args["roll"], args["pitch"])
    raise AssertionError(target)


PARAMETERS = (
    [("patch_roughness", n) for n in ("heights", "spacing", *_PSD_KW)]
    + [
        ("profile_psd", n)
        for n in (
            "heights",
            "spacing",
            "window",
            "nperseg",
            "noverlap",
            "max_gap",
            "max_gap_fraction",
        )
    ]
    + [("fill_gaps", n) for n in ("heights", "spacing", "max_gap", "max_gap_fraction")]
    + [("PatchSpec", n) for n in ("ahead", "size", "spacing", "lateral")]
    + [
        ("grid_points", n)
        for n in (
            "points",
            "spec",
            "min_points",
            "estimate_noise",
            "roll",
            "pitch",
            "level",
            "level_threshold",
        )
    ]
    + [("auto_spacing", n) for n in ("n_points", "spec", "min_points_per_cell")]
    + [("compensate_tilt", n) for n in ("points", "roll", "pitch")]
    + [("Extraction", n) for n in ("patch", "use_imu", "method", "subtract_noise", "auto_spacing")]
    + [
        ("Extraction.from_dict", n)
        for n in ("ahead", "size", "spacing", "lateral", "use_imu", "method", "subtract_noise", "x")
    ]
    + [
        ("frame_features", n)
        for n in ("points", "extraction", "roll", "pitch", "min_points", "min_fill")
    ]
)


@FUZZ
@given(where=st.sampled_from(PARAMETERS), value=HOSTILE)
def test_hostile_parameter_values(where: tuple[str, str], value: Any) -> None:
    target, name = where
    out = assert_bounded(_call, target, name, value, max_bytes=256 * 2**20)
    if isinstance(out, InputError | PatchError):
        assert "\n" not in str(out)
