"""Where a channel's detector pairs sit in the field of view, and which N pairs to simulate.

The PTEP instrument model shipped in litebird_sim names every detector with its wafer
and pixel but points all of them at the boresight (every quaternion is the identity).
A focal plane needs positions, so this module lays a channel's pixels out by a stated
rule (an assumption, not the flight layout):

- the pixels of a channel (those holding an orthogonal T/B pair) fill the telescope's
  field of view, an ellipse of semi-axes ``(a_u, a_v)`` [deg], as a sunflower
  (Vogel) pattern: point i of n at radius ``sqrt((i + 1/2) / n)`` of the ellipse and
  azimuth ``i x 137.5 deg``, a uniform, deterministic filling for any n;
- the points are sorted by azimuth and handed out wafer by wafer in model order, so
  that each wafer holds one angular sector (wafers are contiguous regions).

:func:`choose_pixels` then picks N of them by farthest-point sampling from a first pixel
(the channel's one-pair default): each new pixel is the one farthest from those already
chosen, so the choice spreads over the field of view and the wafers, is reproducible, and
is nested (the N = 2 choice holds the N = 1 one, and so on).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

GOLDEN_ANGLE_RAD = np.pi * (3.0 - np.sqrt(5.0))  # 137.5 deg


@dataclass(frozen=True)
class PixelPosition:
    """A pixel's direction in the focal plane: angle from the boresight and azimuth."""

    theta_deg: float
    phi_deg: float

    @property
    def uv_deg(self) -> np.ndarray:
        """(u, v) = theta (cos phi, sin phi) [deg] (flat-sky coordinates)."""
        phi = np.radians(self.phi_deg)
        return self.theta_deg * np.array([np.cos(phi), np.sin(phi)])


def sunflower_uv_deg(n: int, semi_axes_deg: tuple[float, float]) -> np.ndarray:
    """(n, 2) points filling an ellipse of semi-axes (a_u, a_v) [deg] uniformly:
    u = a_u sqrt((i + 1/2) / n) cos(i g), v = a_v sqrt((i + 1/2) / n) sin(i g), g the
    golden angle."""
    if n < 1:
        raise ValueError(f"sunflower_uv_deg: n = {n}, expected at least 1")
    i = np.arange(n)
    radius = np.sqrt((i + 0.5) / n)
    azimuth = i * GOLDEN_ANGLE_RAD
    return np.stack(
        [semi_axes_deg[0] * radius * np.cos(azimuth), semi_axes_deg[1] * radius * np.sin(azimuth)],
        axis=1,
    )


def lay_out_pixels(
    pixels: list[str], wafers: list[str], semi_axes_deg: tuple[float, float]
) -> dict[str, PixelPosition]:
    """{pixel: position}: the sunflower points sorted by azimuth, handed out in the
    order of ``pixels`` (model order; ``wafers[i]`` the wafer of ``pixels[i]``), wafer
    after wafer, so that each wafer fills one sector of the field of view."""
    if len(pixels) != len(wafers):
        raise ValueError(f"lay_out_pixels: {len(pixels)} pixels but {len(wafers)} wafers")
    uv = sunflower_uv_deg(len(pixels), semi_axes_deg)
    by_azimuth = uv[np.argsort(np.arctan2(uv[:, 1], uv[:, 0]), kind="stable")]
    order = sorted(range(len(pixels)), key=lambda i: (wafers.index(wafers[i]), i))
    positions = {}
    for point, i in zip(by_azimuth, order, strict=True):
        positions[pixels[i]] = PixelPosition(
            float(np.hypot(*point)), float(np.degrees(np.arctan2(point[1], point[0])))
        )
    return positions


def angular_separation_deg(a: PixelPosition, b: PixelPosition) -> float:
    """Great-circle angle between two focal-plane directions [deg]."""
    return float(np.degrees(np.arccos(np.clip(np.dot(unit_vector(a), unit_vector(b)), -1, 1))))


def unit_vector(position: PixelPosition) -> np.ndarray:
    """The direction in the boresight frame (z = boresight): (sin t cos p, sin t sin p, cos t)."""
    theta, phi = np.radians(position.theta_deg), np.radians(position.phi_deg)
    return np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])


def choose_pixels(positions: dict[str, PixelPosition], first: str, n: int) -> list[str]:
    """``n`` pixels by farthest-point sampling from ``first``: each next pixel maximises
    its smallest separation from those chosen (ties to the earlier pixel of ``positions``)."""
    names = list(positions)
    if first not in positions:
        raise ValueError(f"choose_pixels: first pixel {first!r} has no position")
    if not 1 <= n <= len(names):
        raise ValueError(f"choose_pixels: n = {n}, expected 1..{len(names)} (the pixels laid out)")
    vectors = np.array([unit_vector(positions[name]) for name in names])
    chosen = [names.index(first)]
    nearest = vectors @ vectors[chosen[0]]  # cos of the separation from the closest chosen
    for _ in range(n - 1):
        candidate = int(np.argmin(np.where(np.isin(np.arange(len(names)), chosen), 2.0, nearest)))
        chosen.append(candidate)
        nearest = np.maximum(nearest, vectors @ vectors[candidate])
    return [names[i] for i in chosen]


def offset_quaternion(position: PixelPosition) -> np.ndarray:
    """(1, 4) litebird_sim quaternion (x, y, z, w) turning the boresight z into the
    pixel's direction: a rotation by theta about the axis (-sin phi, cos phi, 0)."""
    theta, phi = np.radians(position.theta_deg), np.radians(position.phi_deg)
    axis = np.array([-np.sin(phi), np.cos(phi), 0.0])
    return np.array([[*(axis * np.sin(theta / 2)), np.cos(theta / 2)]])
