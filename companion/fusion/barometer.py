"""The barometer in the fusion: the offset between ellipsoidal height and barometric altitude, learned
from trusted GNSS pairs, gives the camera's ellipsoidal height while GNSS is lost (the registrations'
height measurement and the scale checks between them, gis.align.fine), with its 1-σ."""
from __future__ import annotations

import math
from dataclasses import dataclass

from companion.fusion.gnss_fit import GnssPair
from gis.geodesy import ecef_to_geodetic
from slam.types import AttitudePrior

BARO_OFFSET_GAIN = 0.02  # per trusted GNSS pair (5 Hz): ~10 s time constant
BARO_NOISE_M = 0.3       # barometric height 1-σ beside the offset's (noise 0.15 m, drift 0.02 m/√s over a minute)


def baro_m(prior: AttitudePrior | None) -> float | None:
    """The prior's barometric altitude when it has a finite one, else None."""
    if prior is None or prior.baro_alt_m is None or not math.isfinite(prior.baro_alt_m):
        return None
    return prior.baro_alt_m


def baro_ema(prev: float | None, value: float) -> float:
    """The barometer offset's running mean (and its σ's): BARO_OFFSET_GAIN per trusted pair."""
    return value if prev is None else prev + BARO_OFFSET_GAIN * (value - prev)


@dataclass
class BaroOffset:
    """Ellipsoidal height − barometric altitude (``offset_m``, learned from GNSS) and the GNSS
    vertical 1-σ it was learned from (``sigma_m``); None until a trusted pair with a barometer."""

    offset_m: float | None = None
    sigma_m: float | None = None

    def learn(self, pair: GnssPair, prior: AttitudePrior | None) -> None:
        """Ellipsoidal height − barometric altitude, averaged over trusted GNSS pairs (exponential,
        BARO_OFFSET_GAIN per pair: ~10 s at 5 Hz). The barometer drifts ~0.02 m/√s, so the offset
        stays good to decimetres for minutes after GNSS is lost."""
        baro = baro_m(prior)
        if baro is None or abs(prior.t_s - pair.t_s) > 0.2:
            return
        off = float(ecef_to_geodetic(pair.p_ecef)[2]) - baro
        self.offset_m = baro_ema(self.offset_m, off)
        self.sigma_m = baro_ema(self.sigma_m, pair.v_acc_m)

    def camera_h_ell_m(self, prior: AttitudePrior | None) -> float | None:
        """The camera's ellipsoidal height from the barometer (the offset is learned from pairs,
        which hold the camera centre when the attitude is known), or None without a barometer or an
        offset learned from GNSS."""
        baro = baro_m(prior)
        return None if baro is None or self.offset_m is None else baro + self.offset_m

    def camera_h_sigma_m(self) -> float:
        """camera_h_ell_m's 1-σ: the GNSS vertical accuracy the offset was learned from, and the
        barometer's own."""
        return math.hypot(self.sigma_m, BARO_NOISE_M)
