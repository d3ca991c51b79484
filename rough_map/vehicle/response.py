"""A vehicle's response to ground of PSD R·Ω^w, and the highest speed that keeps its limits.

At speed v (m/s) a profile of one-sided PSD ``G(Ω) = R Ω^w`` (m³/rad, Ω in rad/m) is a
vertical displacement at the wheel at angular frequency ``ω = v Ω``, and a linear model with
transfer function ``H`` responds with variance ``∫ |H(i v Ω)|² G(Ω) dΩ``. The model is the
quarter-car of :class:`~rough_map.vehicle.spec.QuarterCar`: body ``m_s`` on a spring ``k_s``
and damper ``c_s`` over the wheel ``m_u`` on its tyre ``k_t``::

    Z_s / Z_r = k_t (c_s s + k_s) / D,   Z_u / Z_r = k_t (m_s s² + c_s s + k_s) / D,
    D = (m_s s² + c_s s + k_s)(m_u s² + c_s s + k_s + k_t) - (c_s s + k_s)²

Three responses: the body's vertical acceleration weighted by ISO 2631-1 ``Wk``
(:func:`wk_weighting`, the standard's band-limiting, acceleration-velocity and upward-step
filters), the suspension travel ``z_s - z_u`` and the dynamic tyre load ``k_t (z_r - z_u)``
over the static load. With a wheelbase ``L`` and the acceleration taken at the centre
(:attr:`~rough_map.vehicle.spec.Vehicle.acceleration_at`), the body's acceleration is the
mean of the front corner's and the rear's, which sees the same profile ``L / v`` later:
``|(1 + e^(-i ω L / v)) / 2|² = cos²(Ω L / 2)`` times the corner's, the wheelbase filter
(travel and tyre load stay those of a corner).

The spectrum is the measured fit: ``R Ω^w`` over the band the patch measured, extended as the
same power law down to :data:`MIN_WAVENUMBER` (0.05 rad/m, a wavelength of 126 m) and not
beyond the band's short end, which the tyre's contact patch filters out anyway. Since
``G`` is a power law, ``σ²(v) = R v^(-w-1) ∫ |H(iω)|² ω^w dω`` over ``[v Ω_min, v Ω_max]``:
:class:`SpeedTable` tabulates the integral once per vehicle over waviness and speed, so a
whole map's cells get their speed in one vectorised pass. Assumptions: linear, each
corner alike, one track (left and right wheels uncorrelated: no roll; with a wheelbase, no
pitch coupling between the axles), Gaussian ground, the power law holding beyond the band.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rough_map.errors import InputError
from rough_map.vehicle.spec import QuarterCar, Vehicle

__all__ = [
    "MIN_WAVENUMBER",
    "Z95",
    "Response",
    "SpeedTable",
    "quarter_car_transfer",
    "wheelbase_filter",
    "wk_polynomials",
    "wk_sections",
    "wk_weighting",
]

#: Longest wavelength the power law is extended to: Ω = 0.05 rad/m (126 m).
MIN_WAVENUMBER = 0.05
#: One-sided 95 % quantile of the standard normal: the speed held with 95 % confidence
#: takes R at exp(Z95 se_lnR) times its estimate and the worse of w ± Z95 se_w.
Z95 = 1.6448536269514722
#: Waviness nodes of the table (w is clipped to them).
_W_NODES = np.round(np.arange(-4.0, -0.45, 0.05), 10)
#: Patches whose variances at every speed are held at once (3 x 160 x 4096 floats, 16 MB).
_CHUNK = 4096
#: Points of the frequency integral per decade.
_PER_DECADE = 200


def wk_sections() -> list[tuple[list[float], list[float]]]:
    """ISO 2631-1's ``Wk`` as four second-order sections ``(numerator, denominator)``
    (highest power of s first), ISO 2631-1:1997 Annex A: the band limit (high-pass f1 = 0.4
    Hz and low-pass f2 = 100 Hz, Butterworth), the acceleration-velocity transition (f3 = f4
    = 12.5 Hz, Q4 = 0.63) and the upward step (f5 = 2.37 Hz, Q5 = 0.91, f6 = 3.35 Hz,
    Q6 = 0.91; gain (f5 / f6)² below, 1 above)."""
    w1, w2, w3, w4, w5, w6 = (2 * math.pi * f for f in (0.4, 100.0, 12.5, 12.5, 2.37, 3.35))
    q = 1 / math.sqrt(2)
    q4, q5, q6 = 0.63, 0.91, 0.91
    return [
        ([1.0, 0.0, 0.0], [1.0, w1 / q, w1**2]),
        ([0.0, 0.0, w2**2], [1.0, w2 / q, w2**2]),
        ([0.0, w4**2 / w3, w4**2], [1.0, w4 / q4, w4**2]),
        ([1.0, w5 / q5, w5**2], [1.0, w6 / q6, w6**2]),
    ]


def wk_polynomials() -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:func:`wk_sections` multiplied out: ``Wk``'s numerator and denominator."""
    num, den = np.array([1.0]), np.array([1.0])
    for b, a in wk_sections():
        num, den = np.polymul(num, b), np.polymul(den, a)
    return num, den


def wk_weighting(frequency: ArrayLike) -> NDArray[np.float64]:
    """``|Wk|`` at ``frequency`` (Hz)."""
    num, den = wk_polynomials()
    s = 2j * math.pi * np.asarray(frequency, dtype=float)
    return np.asarray(np.abs(np.polyval(num, s) / np.polyval(den, s)), dtype=np.float64)


def quarter_car_transfer(
    car: QuarterCar, omega: ArrayLike
) -> tuple[NDArray[np.complex128], NDArray[np.complex128], NDArray[np.complex128]]:
    """The quarter-car's responses per metre of road displacement at angular frequency
    ``omega`` (rad/s): body acceleration (m/s² per m), suspension travel (m per m) and
    dynamic tyre load (N per m)."""
    s = 1j * np.asarray(omega, dtype=float)
    ms, mu = car.sprung_mass, car.unsprung_mass
    ks, cs, kt = car.suspension_stiffness, car.suspension_damping, car.tyre_stiffness
    body = ms * s**2 + cs * s + ks
    link = cs * s + ks
    den = body * (mu * s**2 + link + kt) - link**2
    zs = kt * link / den
    zu = kt * body / den
    return s**2 * zs, zs - zu, kt * (1 - zu)


def wheelbase_filter(
    omega: NDArray[np.float64], step: NDArray[np.float64], wheelbase: float
) -> NDArray[np.float64]:
    """``cos²(Ω L / 2)`` (``Ω`` in rad/m, ``L`` the wheelbase in m) averaged over each
    step of the integral, ``Ω`` times ``exp(±step / 2)``: where the steps are longer than
    its period (short waves) it is its mean, 1/2, not an aliased sample."""
    x = omega * wheelbase / 2
    width = omega * wheelbase * np.sinh(np.asarray(step) / 2)  # the step's extent in x
    return np.asarray(0.5 + 0.5 * np.cos(2 * x) * np.sinc(width / np.pi), dtype=np.float64)


@dataclass(frozen=True)
class Response:
    """A vehicle's response at one speed to each of N patches (arrays of shape (N,)).

    Attributes
    ----------
    speed : float
        m/s.
    weighted_acceleration : ndarray
        ISO 2631-1 Wk-weighted rms vertical body acceleration, m/s².
    suspension_travel : ndarray
        rms suspension travel, m.
    dynamic_load_ratio : ndarray
        rms dynamic tyre load over the static load, 1.
    band_hz : tuple of float
        Temporal frequencies in Hz the measured band covers at this speed.
    outside : list of str
        The resonances (``"body"``, ``"wheel"``) outside that range: their response rests
        on the power law extended beyond the band.
    """

    speed: float
    weighted_acceleration: NDArray[np.float64]
    suspension_travel: NDArray[np.float64]
    dynamic_load_ratio: NDArray[np.float64]
    band_hz: tuple[float, float]
    outside: list[str]


class SpeedTable:
    """The integrals of one vehicle's responses over power-law ground, by waviness and
    speed, measured over a band of ``band`` rad/m (see the module docstring).

    Parameters
    ----------
    vehicle : Vehicle
        The model and its limits.
    band : tuple of float
        ``(Ω_low, Ω_high)`` in rad/m of the measured PSD (the fit band).
    speeds : int
        Speeds tabulated, geometric from 0.02 m/s to the top speed.
    """

    def __init__(self, vehicle: Vehicle, band: tuple[float, float], speeds: int = 160) -> None:
        lo, hi = (float(b) for b in band)
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo < hi):
            raise InputError(f"band must be 0 < low < high in rad/m, got {band!r}")
        self.vehicle, self.band = vehicle, (lo, hi)
        top = vehicle.limits.top_speed
        self.speeds = np.geomspace(min(0.02, top / 2), top, speeds)
        car = vehicle.quarter_car
        n = max(64, int(math.log10(hi / MIN_WAVENUMBER) * _PER_DECADE))
        omega = np.geomspace(MIN_WAVENUMBER, hi, n)  # rad/m
        ln_omega = np.log(omega)
        # the integrands at every speed (rad/s = v Ω) and the weights of Ω^(w+1) d ln Ω
        t = self.speeds[:, None] * omega[None, :]
        acc, travel, load = quarter_car_transfer(car, t)
        weight = wk_weighting(t / (2 * math.pi))
        gains = np.stack(
            [
                np.abs(acc * weight) ** 2,
                np.abs(travel) ** 2,
                np.abs(load / car.static_load) ** 2,
            ]
        )  # (3, speeds, n)
        powers = np.exp((_W_NODES[:, None] + 1) * ln_omega[None, :])  # (nodes, n)
        step = np.gradient(ln_omega)
        if vehicle.acceleration_at == "centre" and vehicle.wheelbase is not None:
            gains[0] *= wheelbase_filter(omega, step, vehicle.wheelbase)[None, :]
        #: variance per unit R: (3 responses, w nodes, speeds)
        self._table = np.einsum("ksn,wn,n->kws", gains, powers, step)

    def response(self, R: ArrayLike, w: ArrayLike, speed: float) -> Response:
        """The responses at ``speed`` (m/s) to patches ``R`` (m³/rad) and ``w``."""
        if not (math.isfinite(speed) and 0 < speed <= self.speeds[-1] * (1 + 1e-9)):
            raise InputError(
                f"speed must be in (0, {self.speeds[-1]:g}] m/s (the top speed), got {speed!r}"
            )
        R = np.atleast_1d(np.asarray(R, dtype=float))
        shape = R.shape  # any shape: a table's column or a map's layer
        w = np.broadcast_to(np.asarray(w, dtype=float), shape).ravel()
        # between two tabulated speeds each variance grows as a power of v, as in v_max
        ln_v = np.log(self.speeds)
        x = math.log(speed)
        j = int(np.clip(np.searchsorted(ln_v, x), 1, ln_v.size - 1))
        f = (x - ln_v[j - 1]) / (ln_v[j] - ln_v[j - 1])
        table = self._table[:, :, j - 1 : j + 1]  # only the two speeds around it
        var = self._variance(R.ravel(), w, table)  # (3, N, 2)
        a, b = var[..., 0], var[..., 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            logs = np.exp((1 - f) * np.log(a) + f * np.log(b))
        at = np.where((a > 0) & (b > 0), logs, (1 - f) * a + f * b)
        rms = np.sqrt(at).reshape(3, *shape)
        lo, hi = (speed * b / (2 * math.pi) for b in self.band)
        car = self.vehicle.quarter_car
        modes = {"body": car.body_frequency, "wheel": car.wheel_frequency}
        outside = [name for name, f in modes.items() if not lo <= f <= hi]
        return Response(speed, rms[0], rms[1], rms[2], (lo, hi), outside)

    def v_max(
        self,
        R: ArrayLike,
        w: ArrayLike,
        se_lnR: ArrayLike | None = None,
        se_w: ArrayLike | None = None,
    ) -> NDArray[np.float64]:
        """The highest speed in m/s (up to the top speed) below which every limit holds,
        for each patch; NaN where R or w is not finite. With the standard errors, the speed
        that holds with 95 % confidence: R at ``exp(Z95 se_lnR)`` times its estimate, and
        the lower speed of ``w ± Z95 se_w``."""
        R = np.atleast_1d(np.asarray(R, dtype=float))
        shape = R.shape  # any shape: a table's column or a map's layer
        R = R.ravel()
        w = np.broadcast_to(np.asarray(w, dtype=float), shape).ravel()
        read = np.isfinite(R) & np.isfinite(w) & (R > 0)  # a map's unseen cells cost nothing
        out = np.full(R.shape, np.nan)
        r, v = np.asarray(R[read], dtype=float), np.asarray(w[read], dtype=float)
        if se_lnR is None and se_w is None:
            out[read] = self._v_max(r, v)
            return out.reshape(shape)
        up = np.exp(Z95 * np.nan_to_num(_flat(se_lnR, shape)[read]))
        dw = Z95 * np.nan_to_num(_flat(se_w, shape)[read])
        out[read] = np.fmin(self._v_max(r * up, v - dw), self._v_max(r * up, v + dw))
        return out.reshape(shape)

    def _variance(
        self, R: ArrayLike, w: ArrayLike, table: NDArray[np.float64] | None = None
    ) -> NDArray[np.float64]:
        """Variances (3, N, speeds) of the responses to each patch at every speed (of
        ``table``, a slice of the speeds of the whole table)."""
        full = self._table if table is None else table
        R = np.atleast_1d(np.asarray(R, dtype=float))
        w = np.atleast_1d(np.asarray(w, dtype=float))
        pos = (np.clip(w, _W_NODES[0], _W_NODES[-1]) - _W_NODES[0]) / 0.05
        pos = np.nan_to_num(pos)
        i = np.minimum(pos.astype(int), _W_NODES.size - 2)
        frac = (pos - i)[None, :, None]
        var = (1 - frac) * full[:, i, :] + frac * full[:, i + 1, :]
        return np.asarray(var * R[None, :, None], dtype=np.float64)

    def _v_max(self, R: NDArray[np.float64], w: NDArray[np.float64]) -> NDArray[np.float64]:
        """:meth:`v_max` of flat arrays, :data:`_CHUNK` patches at a time (bounded memory
        for a map of millions of cells)."""
        if R.size > _CHUNK:
            return np.concatenate(
                [
                    self._v_max(R[k : k + _CHUNK], w[k : k + _CHUNK])
                    for k in range(0, R.size, _CHUNK)
                ]
            )
        var = self._variance(R, w)
        limits = self.vehicle.limits
        caps = [limits.weighted_acceleration, None, limits.dynamic_load_ratio]
        ok = np.ones(var.shape[1:], dtype=bool)
        for k, cap in enumerate(caps):
            if cap is not None:
                ok &= var[k] <= cap**2
        # the first speed that breaks a limit; v_max is found between it and the one below
        broken = ~ok
        first = np.where(broken.any(axis=1), broken.argmax(axis=1), -1)
        out = np.full(R.shape, self.speeds[-1])
        out[first == 0] = 0.0
        cells = np.flatnonzero(first > 0)
        j = first[cells]
        # each response grows as a power of v between two nodes: interpolate in logs
        frac = np.ones(cells.size)
        with np.errstate(divide="ignore", invalid="ignore"):
            for k, cap in enumerate(caps):
                if cap is None:
                    continue
                lo, hi = var[k, cells, j - 1], var[k, cells, j]
                breaks = hi > cap**2
                a, b = np.log(lo), np.log(hi)
                f = np.where(b > a, (2 * math.log(cap) - a) / (b - a), 1.0)
                frac = np.where(breaks, np.fmin(frac, f), frac)
        ln_v = np.log(self.speeds)
        out[cells] = np.exp(ln_v[j - 1] + np.clip(frac, 0.0, 1.0) * (ln_v[j] - ln_v[j - 1]))
        out[~(np.isfinite(R) & np.isfinite(w) & (R > 0))] = np.nan
        return out


def _flat(values: ArrayLike | None, shape: tuple[int, ...]) -> NDArray[np.float64]:
    """``values`` (0 for None) broadcast to ``shape`` and flattened."""
    if values is None:
        return np.zeros(int(np.prod(shape)))
    return np.broadcast_to(np.asarray(values, dtype=float), shape).ravel()
