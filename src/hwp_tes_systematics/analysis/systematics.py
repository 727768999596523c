"""The sigma_g1 cases of the study and the g1 draws, applied to the linear map model.

For realization ``seed``, detector k of a systematics channel gets g1_k = sigma z_k with
z_k ~ N(0, 1) drawn from the stream ("g1", channel, seed, detector) of the master seed
(``per="detector"``: one g1 per TES, the random population), or the two detectors of
pair j share one z from the stream ("g1", channel, seed, "pair", j) (``per="pair"``: the
paper's g1^i per realization; pair 0's stream is ("g1", channel, seed, "pair")), or every
detector of the channel shares the z of ("g1", channel, seed, "pair") (``per="channel"``:
a residual common to the channel; with one pair, the same draws as ``pair``):
the same z_k for every sigma, so each realization's systematic scales exactly as sigma
wherever the map response is linear. The map of a channel is then

    m(sigma) = m_nosys + sigma sum_k z_k T_k.

Cases are named "nosys" (g1 = 0) and "sigma<value>" (e.g. "sigma1e-3", "sigma2.5e-3").
"""

from __future__ import annotations

import numpy as np

from .. import seeding

NOSYS = "nosys"


def case_name(sigma_g1_per_k: float) -> str:
    """'sigma1e-3' for 1e-3 K^-1, 'sigma2.5e-3' for 2.5e-3 K^-1 (two significant digits)."""
    return f"sigma{sigma_g1_per_k:.1e}".replace("e-0", "e-").replace(".0e", "e")


def case_names(sigma_grid_per_k) -> list[str]:
    """'nosys' followed by one case per sigma of the grid."""
    return [NOSYS, *(case_name(sigma) for sigma in sigma_grid_per_k)]


def sigma_of_case(case: str, sigma_grid_per_k) -> float:
    """sigma_g1 [1/K] of a case name (0 for nosys); ValueError if not on the grid."""
    if case == NOSYS:
        return 0.0
    for sigma in sigma_grid_per_k:
        if case_name(sigma) == case:
            return float(sigma)
    raise ValueError(f"case {case!r}: not 'nosys' nor one of {case_names(sigma_grid_per_k)}")


G1_PER = ("detector", "pair", "channel")


def unit_g1_draws(
    master_seed: int, channel: str, seed: int, detectors, per: str = "detector"
) -> np.ndarray:
    """z_k ~ N(0, 1) of a realization's detectors (pairs in order: T, B, T, B, ...), one per
    detector, per pair or per channel (``per``; see the module docstring)."""
    return _g1_draws(master_seed, (channel, seed), detectors, per)


def instrument_g1_draws(
    master_seed: int, channel: str, instrument: int, detectors, per: str = "detector"
) -> np.ndarray:
    """z_k ~ N(0, 1) of fixed instrument number ``instrument``: the same for every
    realization, from the streams of :func:`unit_g1_draws` with the seed replaced by
    ("instrument", instrument), independent of every seed's own draws. A fixed
    instrument's g1 over many skies and noise draws separates the bias a given focal
    plane carries (the mean) from the scatter it adds."""
    return _g1_draws(master_seed, (channel, "instrument", instrument), detectors, per)


def _g1_draws(master_seed: int, stream: tuple, detectors, per: str) -> np.ndarray:
    """One N(0, 1) per detector from ("g1", *stream, detector); per pair j from
    ("g1", *stream, "pair", j) (j = 0: ("g1", *stream, "pair")); or one for the channel
    from ("g1", *stream, "pair")."""
    if per not in G1_PER:
        raise ValueError(f"per = {per!r}: expected one of {G1_PER}")
    if per == "detector":
        return np.array(
            [seeding.rng(master_seed, "g1", *stream, name).standard_normal() for name in detectors]
        )
    if per == "pair" and len(detectors) % 2:
        raise ValueError(f"per = 'pair': {len(detectors)} detectors, expected pairs")
    n_draws = len(detectors) // 2 if per == "pair" else 1
    z = [
        seeding.rng(master_seed, "g1", *stream, "pair", *([j] if j else [])).standard_normal()
        for j in range(n_draws)
    ]
    return np.repeat(z, len(detectors) // n_draws)


def maps_for_sigma(nosys: np.ndarray, templates: np.ndarray, unit_draws, sigma_g1_per_k: float):
    """m = m_nosys + sigma sum_k z_k T_k (3, npix) [K_CMB]; unobserved pixels stay UNSEEN."""
    if sigma_g1_per_k == 0.0:
        return nosys.copy()
    import healpy as hp

    seen = nosys[0] != hp.UNSEEN
    out = nosys.copy()
    contamination = np.tensordot(np.asarray(unit_draws, dtype=float), templates, axes=1)
    out[:, seen] += sigma_g1_per_k * contamination[:, seen]
    return out
