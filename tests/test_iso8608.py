"""Known answers of the ISO 8608 scale: the paper's Table 1 and Eq. 10."""

import numpy as np
import pytest

from rough_map import iso8608
from rough_map.errors import InputError

# Paper, Table 1: rms in mm over 2 pi / 0.896 ... pi / 0.008 rad/m.
TABLE_1 = {
    "A": 0.37,
    "B": 0.75,
    "C": 1.50,
    "D": 2.99,
    "E": 5.99,
    "F": 11.98,
    "G": 23.95,
    "H": 47.90,
}


@pytest.mark.parametrize("cls", list(TABLE_1))
def test_band_rms_reproduces_table_1(cls):
    rms_mm = iso8608.band_rms(iso8608.PHI0[cls], 0.896, 0.008) * 1e3
    assert rms_mm == pytest.approx(TABLE_1[cls], abs=0.01)


def test_sensitivity_of_the_patio():
    phi = iso8608.sensitivity(2.22e-3, 0.896, 0.008)
    assert phi == pytest.approx(35e-6, rel=0.02)
    assert iso8608.PHI0["C"] < phi < iso8608.PHI0["D"]


def test_sensitivity_inverts_band_rms():
    for cls, phi0 in iso8608.PHI0.items():
        rms = iso8608.band_rms(phi0, 0.896, 0.008)
        assert iso8608.sensitivity(rms, 0.896, 0.008) == pytest.approx(phi0, rel=1e-12), cls


def test_band_rms_general_waviness_matches_numerical_integral():
    from scipy.integrate import quad

    lo, hi = iso8608.waveband(0.896, 0.008)
    for w in (-1.0, -2.4, -3.0):
        expected = np.sqrt(quad(lambda om, w=w: 1e-4 * om**w, lo, hi, limit=200)[0])
        assert iso8608.band_rms(1e-4, 0.896, 0.008, w) == pytest.approx(expected, rel=1e-6)


def test_classes_and_boundaries():
    assert iso8608.iso_class(1e-6) == "A"
    assert iso8608.iso_class(1.99e-6) == "A"
    assert iso8608.iso_class(2.01e-6) == "B"
    assert iso8608.iso_class(393e-6) == "E"
    assert iso8608.iso_class(1734e-6) == "F"
    assert iso8608.iso_class(1.0) == "H"
    assert iso8608.iso_class(np.nan) == ""
    assert list(iso8608.iso_class(np.array([1e-6, 64e-6]))) == ["A", "D"]
    for cls, phi in iso8608.PHI0.items():
        assert iso8608.iso_class(phi) == cls


def test_gd_convention():
    # ISO 8608 quotes class A as Gd(n0 = 0.1 cycle/m) = 16e-6 m^3, i.e. about 1e-6 m^3/rad.
    assert iso8608.gd_to_phi(16e-6) == pytest.approx(1e-6, rel=0.02)
    assert iso8608.phi_to_gd(iso8608.gd_to_phi(3e-5)) == pytest.approx(3e-5)


def test_bad_input():
    with pytest.raises(InputError, match="spacing"):
        iso8608.band_rms(1e-6, 0.896, 0.0)
    with pytest.raises(InputError, match="rms"):
        iso8608.sensitivity(-1.0, 0.896, 0.008)
    with pytest.raises(InputError, match="unknown ISO 8608 class"):
        iso8608.synthesize_profile(64, 0.008, "Z")
    with pytest.raises(InputError, match="length"):
        iso8608.waveband(0.01, 0.008)


def test_synthesis_is_seeded():
    a = iso8608.synthesize_surface((64, 64), 0.008, "D", -2.4, seed=3)
    b = iso8608.synthesize_surface((64, 64), 0.008, "D", -2.4, seed=3)
    c = iso8608.synthesize_surface((64, 64), 0.008, "D", -2.4, seed=4)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)


def test_profile_synthesis_has_the_requested_spectrum():
    """Average periodogram of many synthetic profiles matches phi0 Omega^w (band-limited)."""
    n, b = 256, 0.008
    h = iso8608.synthesize_profile(n, b, 1e-4, -2.5, n_profiles=4000, oversample=1, seed=0)
    spec = np.abs(np.fft.rfft(h, axis=1)) ** 2 * (2 * b / n) / (2 * np.pi)
    omega = 2 * np.pi * np.fft.rfftfreq(n, b)
    k = slice(1, n // 2)
    ratio = spec[:, k].mean(axis=0) / iso8608.power_law(omega[k], 1e-4, -2.5)
    assert np.median(ratio) == pytest.approx(1.0, abs=0.03)
