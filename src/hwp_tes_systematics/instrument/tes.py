"""Steady-state electrothermal model of a voltage-biased TES bolometer.

Purpose: give the physical scale of the gain nonlinearity g1 (and g2) in the
detector response d_NL = (1 + g1 d) d that turns the HWP synchronous signal
into leakage.

Model (SI units throughout):

* Thermal link to the bath: P_bath(T) = K (T^n - Tb^n), so the thermal
  conductance is G(T) = dP_bath/dT = n K T^(n-1). K is fixed by the saturation
  power, Psat := K (Tc^n - Tb^n).
* Resistive transition: R(T, I) = Rn/2 [1 + tanh((T - Tc(I)) / w)], with the
  Ginzburg-Landau suppression of the critical temperature by the bias current,
  Tc(I) = Tc max(0, 1 - (|I| / I_c0)^(2/3)).
* Voltage bias through a Thevenin equivalent (shunt + parasitic resistance
  R_th in series with the TES): I = V_th / (R_th + R(T, I)).
* Steady-state power balance: P_opt + I^2 R(T, I) = P_bath(T).

Solution method: the reduced transition coordinate u = (T - Tc(I)) / w makes
every quantity explicit, R = Rn expit(2u), I = V_th / (R_th + R),
T = Tc(I) + w u, so the operating point is a 1-D root in u of the power
residual f(u) = P_bath(T) - P_opt - I^2 R. R, 1/I and T increase strictly with
u, hence f increases strictly wherever R >= R_th (the Joule power
V_th^2 R / (R_th + R)^2 then falls with R). The physical operating point, the
one reached when biasing down from the normal state, is the root with the
highest temperature: it is the unique root above R = R_th when f < 0 there,
and otherwise the highest sign change found on a grid scan of the low-resistance
side. A TES driven normal by the optical power is the same root at large u,
where R = Rn to machine precision.

Assumptions (not LiteBIRD measurements): n = 3, w = 1 mK, I_c0 = 1 mA,
Rn = 1 ohm, R_th = 0.03 ohm; Tc = 171 mK and Tb = 100 mK follow the LiteBIRD
design (PTEP); Psat ~ 2.5 x the expected optical load.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import brentq
from scipy.special import expit

__all__ = [
    "OperatingPoint",
    "TesParameters",
    "bias_voltage_for_resistance",
    "nonlinearity_coefficients",
    "optical_power_for_resistance",
    "responsivity_a_per_w",
    "solve_operating_point",
    "tes_parameters_for_channel",
]

# brentq tolerances: the responsivity is a finite difference of I(P_opt), so
# the operating point is solved to machine precision.
_XTOL = 1e-15
_RTOL = 4.0 * np.finfo(float).eps
# Below this reduced coordinate R / Rn = expit(2u) < 1e-260: numerically a
# superconductor (used as the monotone-branch start when R_th = 0).
_U_SUPERCONDUCTING = -300.0
# Half-width of the densely scanned part of the transition, in units of w.
_U_TRANSITION = 40.0


def _check(name: str, value: float, is_valid: bool, expected: str) -> None:
    if not is_valid:
        raise ValueError(f"tes.{name} = {value!r}: expected {expected}")


@dataclass(frozen=True, kw_only=True)
class TesParameters:
    """Physical parameters of a voltage-biased TES (SI units)."""

    tc_k: float = 0.171
    """Critical temperature at zero current Tc [K] (LiteBIRD design, PTEP)."""
    tbath_k: float = 0.100
    """Bath temperature Tb [K]."""
    thermal_exponent_n: float = 3.0
    """Exponent n of P_bath = K (T^n - Tb^n) (assumption)."""
    psat_w: float
    """Saturation power Psat = K (Tc^n - Tb^n) [W]; defines K."""
    rn_ohm: float = 1.0
    """Normal resistance Rn [ohm]."""
    transition_width_k: float = 1e-3
    """Width w of R(T) = Rn/2 [1 + tanh((T - Tc(I)) / w)] [K] (assumption)."""
    critical_current_a: float = 1e-3
    """I_c0 of Tc(I) = Tc [1 - (|I| / I_c0)^(2/3)] [A]; math.inf disables it."""
    thevenin_resistance_ohm: float = 0.03
    """Thevenin (shunt + parasitic) resistance R_th in series with the TES [ohm]."""
    bias_voltage_v: float
    """Thevenin bias voltage V_th [V]."""

    def __post_init__(self) -> None:
        _check("tc_k", self.tc_k, math.isfinite(self.tc_k) and self.tc_k > 0, "a temperature > 0 K")
        _check(
            "tbath_k",
            self.tbath_k,
            math.isfinite(self.tbath_k) and self.tbath_k > 0,
            "a temperature > 0 K",
        )
        _check(
            "tbath_k",
            self.tbath_k,
            self.tbath_k < self.tc_k,
            f"a bath temperature below tc_k = {self.tc_k!r} K",
        )
        _check(
            "thermal_exponent_n",
            self.thermal_exponent_n,
            math.isfinite(self.thermal_exponent_n) and self.thermal_exponent_n > 0,
            "an exponent > 0",
        )
        _check(
            "psat_w", self.psat_w, math.isfinite(self.psat_w) and self.psat_w > 0, "a power > 0 W"
        )
        _check(
            "rn_ohm",
            self.rn_ohm,
            math.isfinite(self.rn_ohm) and self.rn_ohm > 0,
            "a resistance > 0 ohm",
        )
        _check(
            "transition_width_k",
            self.transition_width_k,
            math.isfinite(self.transition_width_k) and self.transition_width_k > 0,
            "a width > 0 K",
        )
        _check(
            "critical_current_a",
            self.critical_current_a,
            self.critical_current_a > 0,
            "a current > 0 A (math.inf switches the current dependence off)",
        )
        _check(
            "thevenin_resistance_ohm",
            self.thevenin_resistance_ohm,
            math.isfinite(self.thevenin_resistance_ohm) and self.thevenin_resistance_ohm >= 0,
            "a resistance >= 0 ohm",
        )
        _check(
            "bias_voltage_v",
            self.bias_voltage_v,
            math.isfinite(self.bias_voltage_v) and self.bias_voltage_v >= 0,
            "a voltage >= 0 V",
        )

    @property
    def bath_coefficient_w_per_kn(self) -> float:
        """K = Psat / (Tc^n - Tb^n) [W / K^n]."""
        n = self.thermal_exponent_n
        return self.psat_w / (self.tc_k**n - self.tbath_k**n)

    def bath_power_w(self, temperature_k):
        """P_bath = K (T^n - Tb^n) [W]; T is clipped at 0 K."""
        n = self.thermal_exponent_n
        t_k = np.maximum(temperature_k, 0.0)
        return self.bath_coefficient_w_per_kn * (t_k**n - self.tbath_k**n)

    def critical_temperature_k(self, current_a):
        """Tc(I) = Tc max(0, 1 - (|I| / I_c0)^(2/3)) [K]."""
        suppression = (np.abs(current_a) / self.critical_current_a) ** (2.0 / 3.0)
        return self.tc_k * np.maximum(1.0 - suppression, 0.0)

    def resistance_ohm(self, temperature_k, current_a):
        """R(T, I) = Rn/2 [1 + tanh((T - Tc(I)) / w)] = Rn expit(2 (T - Tc(I)) / w) [ohm]."""
        reduced = (temperature_k - self.critical_temperature_k(current_a)) / self.transition_width_k
        return self.rn_ohm * expit(2.0 * reduced)


@dataclass(frozen=True)
class OperatingPoint:
    """Steady-state operating point(s); arrays with the shape of P_opt."""

    temperature_k: np.ndarray
    resistance_ohm: np.ndarray
    current_a: np.ndarray
    joule_power_w: np.ndarray
    """P_J = I^2 R [W]."""
    tes_voltage_v: np.ndarray
    """V_TES = I R [V]."""
    is_normal: np.ndarray
    """R > 0.99 Rn."""


def _state_at_reduced_coordinate(params: TesParameters, reduced):
    """(R, I, T) at u = (T - Tc(I)) / w: R = Rn expit(2u), I = V_th/(R_th + R), T = Tc(I) + w u."""
    resistance = params.rn_ohm * expit(2.0 * reduced)
    current = params.bias_voltage_v / (params.thevenin_resistance_ohm + resistance)
    temperature = params.critical_temperature_k(current) + params.transition_width_k * reduced
    return resistance, current, temperature


def _power_residual_w(params: TesParameters, p_opt_w: float, reduced):
    """f(u) = P_bath(T) - P_opt - I^2 R [W]; increasing in u wherever R >= R_th."""
    resistance, current, temperature = _state_at_reduced_coordinate(params, reduced)
    return params.bath_power_w(temperature) - p_opt_w - current**2 * resistance


def _solve_reduced_coordinate(params: TesParameters, p_opt_w: float) -> float:
    """Highest-temperature root u of the power balance at one optical power."""
    n = params.thermal_exponent_n
    width = params.transition_width_k
    bias = params.bias_voltage_v
    r_th, r_n = params.thevenin_resistance_ohm, params.rn_ohm

    def residual(reduced):
        return float(_power_residual_w(params, p_opt_w, reduced))

    # Tc(I) <= Tc, so T(u_low) <= Tb - w and f(u_low) < -P_opt - P_J <= 0.
    u_low = (params.tbath_k - params.tc_k) / width - 1.0
    # For u >= 0: R >= Rn/2, P_J <= V^2/R <= 2 V^2/Rn and Tc(I) >= Tc(V/(R_th + Rn/2)),
    # so T(u_high) > T_up with P_bath(T_up) = P_opt + 2 V^2/Rn, hence f(u_high) > 0.
    t_up_k = (
        params.tbath_k**n + (p_opt_w + 2.0 * bias**2 / r_n) / params.bath_coefficient_w_per_kn
    ) ** (1.0 / n)
    tc_half_k = float(params.critical_temperature_k(bias / (r_th + 0.5 * r_n)))
    u_high = max(0.0, (t_up_k - tc_half_k) / width) + 1.0
    # f is strictly increasing above u_star, where R = R_th.
    if r_th == 0.0:
        u_star = _U_SUPERCONDUCTING
    elif r_th < r_n:
        u_star = math.atanh(2.0 * r_th / r_n - 1.0)
    else:
        u_star = math.inf
    u_start = min(max(u_star, u_low), u_high)

    f_start = residual(u_start)
    if f_start < 0.0:
        return brentq(residual, u_start, u_high, xtol=_XTOL, rtol=_RTOL)
    if f_start == 0.0:
        return u_start
    # Latched low-resistance side (R < R_th): scan for the highest sign change.
    grid = np.unique(
        np.concatenate(
            [
                np.linspace(u_low, u_start, 2001),
                np.clip(np.linspace(-_U_TRANSITION, _U_TRANSITION, 4001), u_low, u_start),
            ]
        )
    )
    negative = np.flatnonzero(_power_residual_w(params, p_opt_w, grid) < 0.0)
    if negative.size == 0:
        raise RuntimeError(
            f"no TES operating point found for p_opt_w = {p_opt_w!r} W with {params!r}"
        )
    lower, upper = grid[negative[-1]], grid[negative[-1] + 1]
    if residual(upper) == 0.0:
        return float(upper)
    return brentq(residual, lower, upper, xtol=_XTOL, rtol=_RTOL)


def solve_operating_point(params: TesParameters, p_opt_w) -> OperatingPoint:
    """Steady state of P_opt + I^2 R(T, I) = K (T^n - Tb^n), I = V_th / (R_th + R(T, I)).

    ``p_opt_w`` [W] (scalar or array, >= 0). Where several solutions exist the
    one reached when biasing down from the normal state (highest T) is returned;
    above saturation this is the normal state, R = Rn.
    """
    p_opt_w = np.asarray(p_opt_w, dtype=float)
    if not np.all(np.isfinite(p_opt_w) & (p_opt_w >= 0.0)):
        raise ValueError(f"p_opt_w = {p_opt_w!r}: expected finite optical powers >= 0 W")
    reduced = np.array(
        [_solve_reduced_coordinate(params, float(p)) for p in p_opt_w.ravel()]
    ).reshape(p_opt_w.shape)
    resistance, current, temperature = _state_at_reduced_coordinate(params, reduced)
    return OperatingPoint(
        temperature_k=np.asarray(temperature),
        resistance_ohm=np.asarray(resistance),
        current_a=np.asarray(current),
        joule_power_w=np.asarray(current**2 * resistance),
        tes_voltage_v=np.asarray(current * resistance),
        is_normal=np.asarray(resistance > 0.99 * params.rn_ohm),
    )


def bias_voltage_for_resistance(
    params: TesParameters, p_opt_w: float, resistance_fraction: float
) -> float:
    """Thevenin voltage V_th [V] that puts the TES at R0 = resistance_fraction * Rn at P_opt.

    At R0 the reduced coordinate is u0 = artanh(2 R0/Rn - 1), so T = Tc(I) + w u0 and
    the current solves I^2 R0 = K (T^n - Tb^n) - P_opt (left side increasing, right
    side non-increasing in I); then V_th = I (R_th + R0). The result is checked
    with :func:`solve_operating_point` (R0 must be the highest-temperature root).
    """
    if not 0.0 < resistance_fraction < 1.0:
        raise ValueError(
            f"resistance_fraction = {resistance_fraction!r}: expected a value in (0, 1)"
        )
    if not (math.isfinite(p_opt_w) and p_opt_w >= 0.0):
        raise ValueError(f"p_opt_w = {p_opt_w!r}: expected an optical power >= 0 W")
    if p_opt_w >= params.psat_w:
        raise ValueError(
            f"p_opt_w = {p_opt_w!r} W >= tes.psat_w = {params.psat_w!r} W: at or above "
            "saturation there is no electrothermal operating point in the transition"
        )
    r0_ohm = resistance_fraction * params.rn_ohm
    u0 = math.atanh(2.0 * resistance_fraction - 1.0)

    def joule_excess_w(current_a: float) -> float:
        temperature_k = params.critical_temperature_k(current_a) + params.transition_width_k * u0
        return float(params.bath_power_w(temperature_k) - p_opt_w - current_a**2 * r0_ohm)

    excess_at_zero_current_w = joule_excess_w(0.0)
    if excess_at_zero_current_w <= 0.0:
        raise ValueError(
            f"p_opt_w = {p_opt_w!r} W: the bath power at R0 = {r0_ohm!r} ohm "
            f"(T = {params.tc_k + params.transition_width_k * u0!r} K) does not exceed the "
            "optical power, so no bias reaches that resistance"
        )
    current_high_a = math.sqrt(1.01 * excess_at_zero_current_w / r0_ohm)
    current_a = brentq(joule_excess_w, 0.0, current_high_a, xtol=_XTOL * current_high_a, rtol=_RTOL)
    bias_voltage_v = current_a * (params.thevenin_resistance_ohm + r0_ohm)

    reached = solve_operating_point(replace(params, bias_voltage_v=bias_voltage_v), p_opt_w)
    if abs(float(reached.resistance_ohm) / r0_ohm - 1.0) > 1e-6:
        raise RuntimeError(
            f"bias V_th = {bias_voltage_v!r} V gives R0 = {r0_ohm!r} ohm only on an unstable "
            f"branch; biasing down from the normal state reaches R = "
            f"{float(reached.resistance_ohm)!r} ohm (is R0 below R_th?)"
        )
    return bias_voltage_v


def optical_power_for_resistance(params: TesParameters, resistance_fraction: float) -> float:
    """Optical power P_opt [W] at which the biased TES sits at R = resistance_fraction * Rn.

    Explicit inverse of :func:`solve_operating_point` on the stable branch R >= R_th
    (where the root is unique): u = artanh(2 R/Rn - 1), I = V_th / (R_th + R),
    T = Tc(I) + w u and P_opt = K (T^n - Tb^n) - I^2 R. With resistance_fraction =
    0.99 this is the optical saturation power: above it the TES is normal. Because
    the voltage bias keeps dissipating V_th^2 Rn / (R_th + Rn)^2 in the normal state,
    it lies below Psat.
    """
    if not 0.0 < resistance_fraction < 1.0:
        raise ValueError(
            f"resistance_fraction = {resistance_fraction!r}: expected a value in (0, 1)"
        )
    resistance = resistance_fraction * params.rn_ohm
    if resistance < params.thevenin_resistance_ohm:
        raise ValueError(
            f"resistance_fraction = {resistance_fraction!r}: R = {resistance!r} ohm is below "
            f"tes.thevenin_resistance_ohm = {params.thevenin_resistance_ohm!r} ohm "
            "(unstable branch, not reached when biasing down from the normal state)"
        )
    reduced = math.atanh(2.0 * resistance_fraction - 1.0)
    _, current, temperature = _state_at_reduced_coordinate(params, reduced)
    p_opt_w = float(params.bath_power_w(temperature) - current**2 * resistance)
    if p_opt_w < 0.0:
        raise ValueError(
            f"resistance_fraction = {resistance_fraction!r}: with tes.bias_voltage_v = "
            f"{params.bias_voltage_v!r} V the TES is above R = {resistance!r} ohm even "
            "without optical power"
        )
    return p_opt_w


def responsivity_a_per_w(params: TesParameters, p_opt_w, step_w: float | None = None):
    """Current responsivity S = dI/dP_opt [A/W] by central differences.

    S = [I(P + h) - I(P - h)] / (2 h), with h = ``step_w`` [W], default 1e-4 Psat
    (small against the transition, far above the solver tolerance). Requires P >= h.
    """
    step_w = 1e-4 * params.psat_w if step_w is None else step_w
    if not (math.isfinite(step_w) and step_w > 0.0):
        raise ValueError(f"step_w = {step_w!r}: expected a power step > 0 W")
    p_opt_w = np.asarray(p_opt_w, dtype=float)
    current_up_a = solve_operating_point(params, p_opt_w + step_w).current_a
    current_down_a = solve_operating_point(params, p_opt_w - step_w).current_a
    return (current_up_a - current_down_a) / (2.0 * step_w)


def nonlinearity_coefficients(
    params: TesParameters,
    p0_w: float,
    kelvin_per_watt: float,
    half_range_w: float,
    n_points: int = 41,
    degree: int = 7,
) -> dict:
    """Nonlinearity of the linearly calibrated response around P0.

    d_est(dP) = [I(P0 + dP) - I(P0)] / S0 = c1 dP + c2 dP^2 + c3 dP^3 + ... [W] is
    fitted by least squares (polynomial of ``degree``, ``n_points`` in
    dP in [-half_range_w, +half_range_w]); c1 ~ 1, c2 = S'/(2 S0), c3 = S''/(6 S0).
    With dP = d / C, C = ``kelvin_per_watt`` [K/W]: d_est = d + g1 d^2 + g2 d^3 [K],
    g1 = c2 / C [1/K], g2 = c3 / C^2 [1/K^2]. The default degree 7 keeps c2, c3 free
    of the aliasing of higher orders: near the knee to the normal state the series
    converges slowly (at P0 = 0.4 Psat, half range 0.1 Psat, degree 5 biases g1 by ~1%).

    Returns ``responsivity_a_per_w`` (S0), ``g1_per_k``, ``g2_per_k2``,
    ``dsdp_a_per_w2`` (S' = 2 S0 c2) and ``polynomial_coefficients`` (c0..c_degree,
    ascending, units W^(1-k)).
    """
    if not (math.isfinite(kelvin_per_watt) and kelvin_per_watt > 0.0):
        raise ValueError(f"kelvin_per_watt = {kelvin_per_watt!r}: expected a value > 0 K/W")
    if not (math.isfinite(half_range_w) and 0.0 < half_range_w <= p0_w):
        raise ValueError(f"half_range_w = {half_range_w!r}: expected a power in (0, p0_w] W")
    if not 3 <= degree < n_points:
        raise ValueError(f"degree = {degree!r}: expected 3 <= degree < n_points = {n_points!r}")
    responsivity0 = float(responsivity_a_per_w(params, p0_w))
    offsets_w = np.linspace(-half_range_w, half_range_w, n_points)
    current0_a = float(solve_operating_point(params, p0_w).current_a)
    currents_a = solve_operating_point(params, p0_w + offsets_w).current_a
    d_est_w = (currents_a - current0_a) / responsivity0
    # Fit in the scaled variable x = dP / half_range for conditioning: c_k = a_k / h^k.
    scaled = np.polynomial.polynomial.polyfit(offsets_w / half_range_w, d_est_w, degree)
    coefficients = scaled / half_range_w ** np.arange(degree + 1)
    return {
        "responsivity_a_per_w": responsivity0,
        "g1_per_k": float(coefficients[2] / kelvin_per_watt),
        "g2_per_k2": float(coefficients[3] / kelvin_per_watt**2),
        "dsdp_a_per_w2": float(2.0 * responsivity0 * coefficients[2]),
        "polynomial_coefficients": coefficients,
    }


def tes_parameters_for_channel(
    p_nominal_w: float,
    psat_factor: float = 2.5,
    resistance_fraction: float = 0.7,
    **overrides,
) -> TesParameters:
    """TES for a channel with nominal optical load ``p_nominal_w`` [W].

    Psat = psat_factor * P_nominal (assumption: LiteBIRD designs Psat ~ 2.5x the
    expected optical load) and V_th from :func:`bias_voltage_for_resistance` so that
    R0 = resistance_fraction * Rn at P_nominal. ``overrides`` set the other
    :class:`TesParameters` fields.
    """
    if not (math.isfinite(p_nominal_w) and p_nominal_w > 0.0):
        raise ValueError(f"p_nominal_w = {p_nominal_w!r}: expected an optical power > 0 W")
    if not (math.isfinite(psat_factor) and psat_factor > 1.0):
        raise ValueError(f"psat_factor = {psat_factor!r}: expected a factor > 1")
    derived = {"psat_w", "bias_voltage_v"} & overrides.keys()
    if derived:
        raise TypeError(f"{sorted(derived)} are derived here and cannot be overridden")
    unbiased = TesParameters(psat_w=psat_factor * p_nominal_w, bias_voltage_v=0.0, **overrides)
    bias_voltage_v = bias_voltage_for_resistance(unbiased, p_nominal_w, resistance_fraction)
    return replace(unbiased, bias_voltage_v=bias_voltage_v)
