"""Is the GIS model where it says it is? Its georeference checked against GNSS while GNSS is good.

Beyond the papers (both assume a model georeferenced to centimetres: photogrammetry, a city's
digital twin). Models users actually fly with are often metres off: OSM footprints traced over
offset imagery, a city mesh in the wrong datum realisation, Google's tiles in places. A GIS
registration then lands the camera where the *model* puts it, and after a GNSS loss the fixes
converge on that offset while their covariance claims the configured ``model_sigma_m``: with a
model 3 m off, 82 % of the fixes 20–25 s into a denial of the `nominal` flight were beyond 3σ
(docs/BENCHMARKS.md, "A GIS model that is metres off").

The offset is observable while GNSS is good: each registration's ICP result *alone* (before the
Kalman update that blends in its prior) puts the camera where the model says, and the concurrent
GNSS fit puts it where GNSS says. Their difference d_k = b + e_k measures the model's offset b
(model − truth, ENU metres), with e_k ~ N(0, S_k), S_k = the ICP's translation covariance + the
GNSS fit's. Registrations at least MIN_SPACING_S apart are taken as independent (the GNSS errors'
correlation time is ~10–20 s). Information-weighted mean over the flight:
b̂ = (Σ S_k⁻¹)⁻¹ Σ S_k⁻¹ d_k, P_b = (Σ S_k⁻¹)⁻¹.

The S_k are what the registration and the GNSS fit claim, and both claim conservatively (the
ICP's basin term was calibrated for the fixes' integrity): on a `loop` flight with a model 3.4 m
off, the six d_k scattered about b̂ with a variance factor α ≈ 0.25–0.29 of the claimed one, so a
test on the claimed S_k found the offset only after ~10 registrations (over 3 minutes of GNSS).
The variance factor is therefore estimated from the data, as a least-squares adjustment's
a-posteriori variance of unit weight (Koch 1999, §4.2): α = r / (3(n − 1)),
r = Σ (d_k − b̂)ᵀ S_k⁻¹ (d_k − b̂), and the test is Fisher's F in place of a χ²:

    T = b̂ᵀ (α P_b + σ_model² I)⁻¹ b̂ / 3  ≤  F(3, 3(n − 1); 99.9 %)

holds the model as georeferenced as configured (no correction, ``model_sigma_m``), as do fewer
than MIN_REGISTRATIONS measurements. Beyond it the model is corrected by b̂ with
σ = max(√λ_max(max(α, 1) P_b), σ_model): the claimed covariances are never shrunk for the
correction's σ. A false alarm (0.1 % per test on an accurate model) costs accuracy, not
integrity, since b̂ is then an unbiased estimate with its own covariance. Offsets larger than the ICP's basin / ``max_jump_m``
(~5 m) give refused registrations and so no measurement: the registrations stay refused, which is
safe, and the log says why.

Evidence carries over between flights at the same site (``GeorefEvidence``, kept by gis.cache with
the model): the measurements of different flights are independent (GNSS errors decorrelate within
seconds to minutes, not days) and the model's offset is the same, so their sums simply add. A
flight too short to find an offset alone (`nominal`'s 63 s of GNSS give 3 registrations) then
starts from what the earlier flights measured, and a model found off is corrected from the
first frame.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.stats import f as fisher_f

TEST_LEVEL = 0.999        # the F test's confidence that a model it corrects is off
MIN_REGISTRATIONS = 3     # measurements before the test may reject the configured accuracy
MIN_SPACING_S = 10.0      # registrations closer than this share their GNSS error: only the first counts


@dataclass(frozen=True)
class IcpMeasurement:
    """Where one registration's ICP alone (before its Kalman update) put the camera at its crop
    centre, in the GIS model's frame *as loaded* (no georeference correction): p_ecef_m (3,) ECEF
    metres, and its covariance cov_enu_m2 (3, 3) in local ENU axes."""

    p_ecef_m: np.ndarray
    cov_enu_m2: np.ndarray


@dataclass(frozen=True)
class GeorefCorrection:
    """The GIS model's georeference error: offset_enu_m (3,) = model − truth in the ENU axes of the
    model's origin, metres (the model is shifted by −offset_enu_m before use); sigma_m: 1-σ of the
    corrected georeference (what replaces ``model_sigma_m``)."""

    offset_enu_m: np.ndarray
    sigma_m: float
    n: int = 0  # registrations it was estimated from

    def describe(self) -> str:
        e, n, u = self.offset_enu_m
        return (f"GIS model georeference off by {np.hypot(e, n):.2f} m horizontally (east {e:+.2f}, north {n:+.2f}, "
                f"up {u:+.2f} m; 1-σ {self.sigma_m:.2f} m, {self.n} registrations vs GNSS)")


@dataclass(frozen=True)
class GeorefEvidence:
    """The sufficient statistics of measurements d_k, S_k (module doc), in ENU metres:
    info = Σ S_k⁻¹ (3, 3) [m⁻²], info_d = Σ S_k⁻¹ d_k (3,) [m⁻¹], dWd = Σ d_kᵀ S_k⁻¹ d_k, n
    measurements. What a flight hands to the next one at the same site (gis.cache)."""

    info: np.ndarray
    info_d: np.ndarray
    dWd: float
    n: int

    def __post_init__(self):
        info, info_d = np.asarray(self.info, float), np.asarray(self.info_d, float)
        if info.shape != (3, 3) or info_d.shape != (3,) or self.n < 0 or not (
                np.all(np.isfinite(info)) and np.all(np.isfinite(info_d)) and np.isfinite(self.dWd) and self.dWd >= 0):
            raise ValueError(f"georeference evidence: expected a finite 3×3 information, 3-vector, dWd ≥ 0 and n ≥ 0, "
                             f"got shapes {info.shape} / {info_d.shape}, dWd {self.dWd}, n {self.n}")
        if self.n > 0 and np.linalg.eigvalsh(0.5 * (info + info.T))[0] <= 0:
            raise ValueError("georeference evidence: the information matrix is not positive definite")
        object.__setattr__(self, "info", info)
        object.__setattr__(self, "info_d", info_d)


@dataclass
class GeorefCheck:
    """Accumulates d_k (ENU m) with covariance S_k (module doc) and decides on a correction."""

    model_sigma_m: float
    info: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))  # Σ S_k⁻¹
    info_d: np.ndarray = field(default_factory=lambda: np.zeros(3))     # Σ S_k⁻¹ d_k
    dWd: float = 0.0                                                    # Σ d_kᵀ S_k⁻¹ d_k
    n: int = 0
    last_t_s: float = -np.inf
    stat: float = 0.0      # T after the latest correction() (module doc)
    critical: float = np.inf  # ... and its critical value F(3, 3(n − 1); TEST_LEVEL)
    alpha: float = 1.0     # ... and the variance factor α

    def add(self, t_s: float, d_enu_m: np.ndarray, S_enu_m2: np.ndarray) -> bool:
        """One registration's ICP-minus-GNSS camera position (ENU m) and its covariance; False
        (ignored) within MIN_SPACING_S of the last one taken or with a non-finite or not
        positive-definite covariance."""
        d = np.asarray(d_enu_m, float).reshape(3)
        S = 0.5 * (np.asarray(S_enu_m2, float) + np.asarray(S_enu_m2, float).T)
        if t_s - self.last_t_s < MIN_SPACING_S or not (np.all(np.isfinite(d)) and np.all(np.isfinite(S))):
            return False
        if np.linalg.eigvalsh(S)[0] <= 0:
            return False
        W = np.linalg.inv(S)
        self.info += W
        self.info_d += W @ d
        self.dWd += float(d @ W @ d)
        self.n += 1
        self.last_t_s = t_s
        return True

    @property
    def evidence(self) -> GeorefEvidence:
        """Everything measured so far (earlier flights' evidence included)."""
        return GeorefEvidence(self.info.copy(), self.info_d.copy(), self.dWd, self.n)

    def add_evidence(self, e: GeorefEvidence) -> None:
        """Earlier flights' measurements (independent of this flight's: module doc)."""
        self.info += e.info
        self.info_d += e.info_d
        self.dWd += e.dWd
        self.n += e.n

    def correction(self) -> GeorefCorrection | None:
        """The correction the measurements so far call for (module doc), or None: the model is as
        georeferenced as configured."""
        if self.n < MIN_REGISTRATIONS:
            self.stat, self.critical, self.alpha = 0.0, np.inf, 1.0
            return None
        P = np.linalg.inv(self.info)
        b = P @ self.info_d
        dof = 3 * (self.n - 1)
        r = max(self.dWd - float(b @ self.info @ b), 0.0)  # Σ (d_k − b̂)ᵀ S_k⁻¹ (d_k − b̂)
        self.alpha = max(r / dof, 1e-6)
        self.stat = float(b @ np.linalg.solve(self.alpha * P + self.model_sigma_m**2 * np.eye(3), b)) / 3
        self.critical = float(fisher_f.ppf(TEST_LEVEL, 3, dof))
        if self.stat <= self.critical:
            return None
        sigma = max(float(np.sqrt(max(self.alpha, 1.0) * np.linalg.eigvalsh(P)[-1])), self.model_sigma_m)
        return GeorefCorrection(b, sigma, self.n)
