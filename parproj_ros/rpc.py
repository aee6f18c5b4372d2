"""Rational polynomial (RPC) sensor models: formats, ground <-> image, virtual GCP (paper 2).

An RPC (NITF RPC00B) maps ground (longitude, latitude in degrees on the WGS84 ellipsoid, height in
metres above the WGS84 ellipsoid) to image (line, sample) as ratios of cubic polynomials of the
normalized coordinates ``L = (lon - long_off) / long_scale``, ``P = (lat - lat_off) / lat_scale``,
``H = (h - height_off) / height_scale``::

    line   = line_scale * num_l(L, P, H) / den_l(L, P, H) + line_off
    sample = samp_scale * num_s(L, P, H) / den_s(L, P, H) + samp_off

with the 20 terms in RPC00B order (:data:`RPC00B_TERMS`).

Pixel convention of this project: continuous image coordinates, pixel centres at integers,
(0, 0) = centre of the first pixel (first line, first sample). Per format, as found in the file
and converted on reading (every model held by :class:`RPCModel` is in this convention):

* NITF RPC00B, ``_RPC.TXT``, ``.RPB``: (0, 0) = centre of the first pixel; no conversion.
* GeoTIFF RPCCoefficientTag (50844): GDAL copies its RPC metadata (RPC00B convention) into the
  tag unchanged; no conversion.
* OSSIM ``.geom`` keyword list: 0-based, pixel centres at integers; no conversion.
* DIMAP v2 (Pleiades 1A/1B, SPOT 6/7) ``RPC_*.XML``: (1, 1) = centre of the first pixel;
  ``line_off - 1``, ``samp_off - 1``.
* DIMAP v3 (Pleiades Neo): origin given by ``FIRST_COL`` of ``ImagetoGround_Validity_Domain``
  (0 for PNEO); ``- FIRST_COL``.

Evidence for DIMAP v2: the DIMAP XML and the OSSIM .geom of the same Pleiades scene (Mont
Ventoux, tests/data/ventoux) carry identical coefficients, but LINE_OFF / SAMP_OFF of the XML are
21110.5 / 19208.5 and those of the .geom 21109.5 / 19207.5; projections through the two differ by
exactly (1, 1) px (tests/test_rpc.py). GDAL's Pleiades reader makes the same correction (centre
of the upper-left pixel is (1, 1) in DIMAP v2, FIRST_COL of the validity domain since DIMAP v3),
and the RPC00B offsets refer to pixel centres (GDAL issue 3946).

Validity domain: an RPC declares where it was fitted (normalized |L|, |P|, |H|, |line|, |sample|
<= 1.1). That is advice, not a limit: the formula is evaluated wherever asked, as GDAL's RPC
transformer, rpcm and s2p do. Many distributed crops keep the parent scene's LINE_OFF / SAMP_OFF
with scales fitted to the crop, so that every pixel lies tens of scale units outside the declared
domain while the model is exact there. :meth:`RPCModel.project` and :meth:`RPCModel.localize`
therefore evaluate everywhere by default (``domain="advice"``); ``domain="limit"`` restores the
hard limit (used by :func:`virtual_gcp`, the paper-2 experiment). What is really wrong is refused
by the importer (parproj_ros/scene_import.py): non-finite coefficients, a localization that does
not converge, a denominator crossing zero over the image (:meth:`RPCModel.denominator_check`).

Ground frames: :func:`ecef_from_geodetic` / :func:`geodetic_from_ecef` (WGS84) and
:class:`LocalTangentPlane` (east, north, up, metres) give the local Cartesian object frame of the
parallel projection model (Z up). Heights are always ellipsoidal here; SRTM heights are above the
geoid (EGM96): :func:`srtm_height` adds a geoid undulation only if one is supplied (it is about
50 m in the western Alps and Provence, so ignoring it shifts every virtual point by that much in
height, which a parallel projection fit absorbs almost entirely).
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .geometry.estimation import AffineEstimate, estimate_affine
from .geometry.navigation import SceneFrame

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
#: A DEM: (longitude deg, latitude deg) arrays -> WGS84 ellipsoidal height, metres (NaN = none).
HeightFunction = Callable[[FloatArray, FloatArray], FloatArray]
#: What to do with points that fail (outside a limiting domain, not converged, not finite).
Outside = Literal["raise", "nan", "ignore"]
#: Whether the declared validity domain is advice (evaluate anywhere) or a hard limit.
Domain = Literal["advice", "limit"]

#: The 20 RPC00B terms (L longitude, P latitude, H height, all normalized).
RPC00B_TERMS: tuple[str, ...] = (
    "1", "L", "P", "H", "LP", "LH", "PH", "LL", "PP", "HH",
    "PLH", "LLL", "LPP", "LHH", "LLP", "PPP", "PHH", "LLH", "PPH", "HHH",
)  # fmt: skip
#: (power of L, power of P, power of H) of each RPC00B term.
_POWERS: tuple[tuple[int, int, int], ...] = tuple(
    (t.count("L"), t.count("P"), t.count("H")) for t in RPC00B_TERMS
)
#: RPC00A order as indices into RPC00B: ``b = a[_A_TO_B]`` (A puts PLH before the squares).
_A_TO_B = np.array([0, 1, 2, 3, 4, 5, 6, 8, 9, 10, 7, 11, 12, 13, 14, 15, 16, 17, 18, 19])
#: Normalized coordinates beyond this magnitude are outside the validity domain.
DOMAIN_LIMIT = 1.1
#: The test applied: DOMAIN_LIMIT plus rounding (1.1 * scale + off may normalize to 1.1 + 2e-16).
_LIMIT = DOMAIN_LIMIT * (1.0 + 1e-12)
#: GeoTIFF RPCCoefficientTag (92 doubles).
RPC_TIFF_TAG = 50844

# WGS84
WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
_B = WGS84_A * (1.0 - WGS84_F)
_E2 = WGS84_F * (2.0 - WGS84_F)
_EP2 = _E2 / (1.0 - _E2)


class RPCError(ValueError):
    """Base class of the errors of this module."""


class RPCFormatError(RPCError):
    """A file is not in a known RPC format, or a key / coefficient is missing or malformed."""


class RPCDomainError(RPCError):
    """Coordinates outside the RPC's validity domain (normalized magnitude > DOMAIN_LIMIT)."""


class RPCConvergenceError(RPCError):
    """The Newton iteration of :meth:`RPCModel.localize` did not reach the tolerance."""


# ---------------------------------------------------------------------------------------------
# Polynomial terms


def _terms(L: FloatArray, P: FloatArray, H: FloatArray) -> FloatArray:
    """The 20 RPC00B terms, shape (..., 20)."""
    one = np.ones_like(L)
    return np.stack(
        [
            one, L, P, H, L * P, L * H, P * H, L * L, P * P, H * H,
            P * L * H, L**3, L * P * P, L * H * H, L * L * P, P**3, P * H * H, L * L * H,
            P * P * H, H**3,
        ],
        axis=-1,
    )  # fmt: skip


def _terms_dl(L: FloatArray, P: FloatArray, H: FloatArray) -> FloatArray:
    """d(terms)/dL, shape (..., 20)."""
    z = np.zeros_like(L)
    one = np.ones_like(L)
    return np.stack(
        [
            z, one, z, z, P, H, z, 2 * L, z, z,
            P * H, 3 * L * L, P * P, H * H, 2 * L * P, z, z, 2 * L * H, z, z,
        ],
        axis=-1,
    )  # fmt: skip


def _terms_dp(L: FloatArray, P: FloatArray, H: FloatArray) -> FloatArray:
    """d(terms)/dP, shape (..., 20)."""
    z = np.zeros_like(L)
    one = np.ones_like(L)
    return np.stack(
        [
            z, z, one, z, L, z, H, z, 2 * P, z,
            L * H, z, 2 * L * P, z, L * L, 3 * P * P, H * H, z, 2 * P * H, z,
        ],
        axis=-1,
    )  # fmt: skip


def _coeff(values: ArrayLike, name: str) -> FloatArray:
    a = np.array(values, dtype=np.float64).reshape(-1)
    if a.shape != (20,):
        raise RPCFormatError(f"{name}: 20 coefficients needed, got {a.size}")
    if not np.all(np.isfinite(a)):
        bad = [i + 1 for i in np.flatnonzero(~np.isfinite(a))]
        raise RPCFormatError(f"{name}: coefficients must be finite, not at {bad} (1-based)")
    a.setflags(write=False)
    return a


def _handle(bad: BoolArray, outside: Outside, error: type[RPCError], message: str) -> None:
    if outside == "raise" and np.any(bad):
        raise error(f"{int(np.count_nonzero(bad))} of {bad.size} points {message}")


# ---------------------------------------------------------------------------------------------
# The model


@dataclass(frozen=True, eq=False)
class RPCModel:
    """An RPC00B model in this project's pixel convention (module docstring).

    Attributes:
        line_off: line offset, pixels (0 = centre of the first line).
        samp_off: sample offset, pixels (0 = centre of the first sample).
        lat_off: latitude offset, degrees (WGS84 geodetic).
        long_off: longitude offset, degrees.
        height_off: height offset, metres above the WGS84 ellipsoid.
        line_scale: line scale, pixels.
        samp_scale: sample scale, pixels.
        lat_scale: latitude scale, degrees.
        long_scale: longitude scale, degrees.
        height_scale: height scale, metres.
        line_num_coeff: 20 numerator coefficients of the line, RPC00B order.
        line_den_coeff: 20 denominator coefficients of the line.
        samp_num_coeff: 20 numerator coefficients of the sample.
        samp_den_coeff: 20 denominator coefficients of the sample.
        err_bias: RMS bias error, metres per horizontal axis (-1 = unknown).
        err_rand: RMS random error, metres per horizontal axis (-1 = unknown).

    """

    line_off: float
    samp_off: float
    lat_off: float
    long_off: float
    height_off: float
    line_scale: float
    samp_scale: float
    lat_scale: float
    long_scale: float
    height_scale: float
    line_num_coeff: FloatArray
    line_den_coeff: FloatArray
    samp_num_coeff: FloatArray
    samp_den_coeff: FloatArray
    err_bias: float = -1.0
    err_rand: float = -1.0
    _num: FloatArray = field(init=False, repr=False)
    _den: FloatArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        for name in ("line_num_coeff", "line_den_coeff", "samp_num_coeff", "samp_den_coeff"):
            object.__setattr__(self, name, _coeff(getattr(self, name), name))
        for name in _SCALARS:
            value = float(getattr(self, name))
            if not math.isfinite(value):
                raise RPCFormatError(f"{name} must be finite, got {value}")
            object.__setattr__(self, name, value)
        for name in ("line_scale", "samp_scale", "lat_scale", "long_scale", "height_scale"):
            if getattr(self, name) == 0.0:
                raise RPCFormatError(f"{name} must not be zero")
        object.__setattr__(self, "err_bias", float(self.err_bias))
        object.__setattr__(self, "err_rand", float(self.err_rand))
        object.__setattr__(
            self, "_num", np.stack([self.line_num_coeff, self.samp_num_coeff], axis=1)
        )
        object.__setattr__(
            self, "_den", np.stack([self.line_den_coeff, self.samp_den_coeff], axis=1)
        )

    # -- conversions ---------------------------------------------------------------------------

    @property
    def coefficients(self) -> FloatArray:
        """(4, 20): line num, line den, sample num, sample den (RPC00B order)."""
        return np.stack(
            [self.line_num_coeff, self.line_den_coeff, self.samp_num_coeff, self.samp_den_coeff]
        )

    def as_vector(self) -> FloatArray:
        """The 92 values of the GeoTIFF RPCCoefficientTag, in its order.

        ERR_BIAS, ERR_RAND, LINE_OFF, SAMP_OFF, LAT_OFF, LONG_OFF, HEIGHT_OFF, LINE_SCALE,
        SAMP_SCALE, LAT_SCALE, LONG_SCALE, HEIGHT_SCALE, then the four 20-coefficient arrays
        (line num, line den, sample num, sample den). Offsets in this project's convention.
        """
        head = [self.err_bias, self.err_rand] + [getattr(self, n) for n in _SCALARS]
        return np.concatenate([np.array(head, dtype=np.float64), self.coefficients.ravel()])

    @classmethod
    def from_vector(cls, values: ArrayLike) -> RPCModel:
        """Inverse of :meth:`as_vector` (92 values)."""
        v = np.asarray(values, dtype=np.float64).reshape(-1)
        if v.shape != (92,):
            raise RPCFormatError(f"an RPC vector has 92 values, got {v.size}")
        scalars = {name: float(v[2 + i]) for i, name in enumerate(_SCALARS)}
        c = v[12:].reshape(4, 20)
        return cls(
            **scalars,
            line_num_coeff=c[0],
            line_den_coeff=c[1],
            samp_num_coeff=c[2],
            samp_den_coeff=c[3],
            err_bias=float(v[0]),
            err_rand=float(v[1]),
        )

    def shifted(self, d_line: float, d_sample: float) -> RPCModel:
        """The same model with image coordinates shifted: line' = line + d_line (pixels).

        E.g. ``shifted(-5000, -5000)`` is the model of a crop whose first pixel is pixel
        (5000, 5000) of this model's image.
        """
        v = self.as_vector()
        v[2] += d_line
        v[3] += d_sample
        return RPCModel.from_vector(v)

    def renormalized(self, **offsets_scales: float) -> RPCModel:
        """The same mapping with other offsets and scales (exact re-expansion of the cubics).

        Any of ``line_off``, ..., ``height_scale`` (keywords, same units as the attributes) may
        be given; the others stay. The ground substitution ``L = a L' + b`` (a = new scale / old
        scale, b = (new offset - old offset) / old scale; likewise P, H) is expanded binomially
        into the 20 RPC00B terms, so a monomial of total degree d in pure rescaling (b = 0) has
        its coefficient multiplied by a^d. The image side: ``line = ls N / D + lo`` becomes
        ``ls' N' / D + lo'`` with ``N' = (ls N + (lo - lo') D) / ls'``. Used for the
        "parent offsets, crop scales" convention of distributed crops (module docstring).

        Raises:
            RPCFormatError: an unknown keyword, or a zero / non-finite value.

        """
        unknown = set(offsets_scales) - set(_SCALARS)
        if unknown:
            raise RPCFormatError(f"renormalized: unknown keywords {sorted(unknown)}")
        new = {n: float(offsets_scales.get(n, getattr(self, n))) for n in _SCALARS}
        pairs = (
            ("long_off", "long_scale"),
            ("lat_off", "lat_scale"),
            ("height_off", "height_scale"),
        )
        subst = []
        for off, scale in pairs:
            a = new[scale] / getattr(self, scale)
            b = (new[off] - getattr(self, off)) / getattr(self, scale)
            # t[i, m]: coefficient of u'^m in (a u' + b)^i, i, m = 0..3
            t = np.zeros((4, 4))
            for i in range(4):
                for m in range(i + 1):
                    t[i, m] = math.comb(i, m) * a**m * b ** (i - m)
            subst.append(t)

        def expand(c: FloatArray) -> FloatArray:
            dense = np.zeros((4, 4, 4))
            for coef, (i, j, k) in zip(c, _POWERS, strict=True):
                dense[i, j, k] += coef
            out = np.einsum("ijk,im,jn,ko->mno", dense, *subst)
            return np.array([out[i, j, k] for i, j, k in _POWERS])

        ln, ld, sn, sd = (expand(c) for c in self.coefficients)
        ln = (self.line_scale * ln + (self.line_off - new["line_off"]) * ld) / new["line_scale"]
        sn = (self.samp_scale * sn + (self.samp_off - new["samp_off"]) * sd) / new["samp_scale"]
        return RPCModel(
            **new,
            line_num_coeff=ln / ld[0],
            line_den_coeff=ld / ld[0],
            samp_num_coeff=sn / sd[0],
            samp_den_coeff=sd / sd[0],
            err_bias=self.err_bias,
            err_rand=self.err_rand,
        )

    # -- normalization -------------------------------------------------------------------------

    def normalize_ground(
        self, lon: ArrayLike, lat: ArrayLike, h: ArrayLike
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(lon deg, lat deg, h m) -> normalized (L, P, H), broadcast shape."""
        lo, la, hh = np.broadcast_arrays(
            np.asarray(lon, dtype=np.float64),
            np.asarray(lat, dtype=np.float64),
            np.asarray(h, dtype=np.float64),
        )
        return (
            (lo - self.long_off) / self.long_scale,
            (la - self.lat_off) / self.lat_scale,
            (hh - self.height_off) / self.height_scale,
        )

    def in_domain(self, lon: ArrayLike, lat: ArrayLike, h: ArrayLike) -> BoolArray:
        """Whether ground points lie in the validity domain (all |L|, |P|, |H| <= 1.1)."""
        L, P, H = self.normalize_ground(lon, lat, h)
        with np.errstate(invalid="ignore"):
            return np.asarray(
                (np.abs(L) <= _LIMIT) & (np.abs(P) <= _LIMIT) & (np.abs(H) <= _LIMIT)
            )

    # -- ground -> image -----------------------------------------------------------------------

    def _ratios(self, L: FloatArray, P: FloatArray, H: FloatArray) -> tuple[FloatArray, ...]:
        t = _terms(L, P, H)
        num = t @ self._num
        den = t @ self._den
        return t, num, den

    def project(
        self,
        lon_deg: ArrayLike,
        lat_deg: ArrayLike,
        h_m: ArrayLike,
        *,
        outside: Outside = "raise",
        domain: Domain = "advice",
    ) -> tuple[FloatArray, FloatArray]:
        """Ground -> image.

        Args:
            lon_deg: longitude, degrees (WGS84), any shape (broadcast with the others).
            lat_deg: latitude, degrees (WGS84 geodetic).
            h_m: height above the WGS84 ellipsoid, metres.
            outside: for points that fail (outside the domain when ``domain == "limit"``, or a
                non-finite result: a zero denominator): ``"raise"``, ``"nan"`` (NaN
                coordinates) or ``"ignore"`` (return what the polynomials give).
            domain: ``"advice"`` (default): evaluate everywhere, as GDAL does; ``"limit"``:
                points outside the declared validity domain (|normalized| > 1.1) fail.

        Returns:
            (line, sample), pixels, this project's convention, float64, the broadcast shape.

        Raises:
            RPCDomainError: a point fails and ``outside == "raise"``.

        """
        L, P, H = self.normalize_ground(lon_deg, lat_deg, h_m)
        if domain == "limit":
            bad = ~self.in_domain(lon_deg, lat_deg, h_m)
            _handle(bad, outside, RPCDomainError, "are outside the RPC validity domain")
        else:
            bad = np.zeros(L.shape, dtype=bool)
        _, num, den = self._ratios(L, P, H)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            line = num[..., 0] / den[..., 0] * self.line_scale + self.line_off
            sample = num[..., 1] / den[..., 1] * self.samp_scale + self.samp_off
            inputs_ok = np.isfinite(L) & np.isfinite(P) & np.isfinite(H)
            blown = inputs_ok & ~(np.isfinite(line) & np.isfinite(sample))
        _handle(blown & ~bad, outside, RPCDomainError, "project to infinity (zero denominator)")
        if outside == "nan":
            bad = bad | blown
            line = np.where(bad, np.nan, line)
            sample = np.where(bad, np.nan, sample)
        return np.asarray(line, dtype=np.float64), np.asarray(sample, dtype=np.float64)

    def denominators(
        self, lon_deg: ArrayLike, lat_deg: ArrayLike, h_m: ArrayLike
    ) -> tuple[FloatArray, FloatArray]:
        """The line and sample denominators (dimensionless) at ground points."""
        L, P, H = self.normalize_ground(lon_deg, lat_deg, h_m)
        _, _, den = self._ratios(L, P, H)
        return np.asarray(den[..., 0]), np.asarray(den[..., 1])

    def denominator_check(
        self, lon_deg: ArrayLike, lat_deg: ArrayLike, h_m: ArrayLike
    ) -> str | None:
        """Why the denominators make the model unusable over these ground points, or None.

        A denominator that changes sign (or comes within 1e-6 of zero relative to its largest
        magnitude) between the points crosses zero inside the area they span: the projection
        goes through infinity there.
        """
        for name, d in zip(
            ("line", "sample"), self.denominators(lon_deg, lat_deg, h_m), strict=True
        ):
            d = d[np.isfinite(d)]
            if d.size == 0:
                continue
            big = float(np.abs(d).max())
            if d.min() < 0.0 < d.max() or float(np.abs(d).min()) <= 1e-6 * big:
                return (
                    f"the {name} denominator crosses zero over the image "
                    f"(from {float(d.min()):.3g} to {float(d.max()):.3g})"
                )
        return None

    def normalized_image_range(
        self, lines: tuple[float, float], samples: tuple[float, float]
    ) -> tuple[tuple[float, float], tuple[float, float]]:
        """Normalized (line, sample) ranges of an image rectangle: ((lo, hi), (lo, hi))."""
        ln = sorted((v - self.line_off) / self.line_scale for v in lines)
        sn = sorted((v - self.samp_off) / self.samp_scale for v in samples)
        return (ln[0], ln[-1]), (sn[0], sn[-1])

    # -- image -> ground -----------------------------------------------------------------------

    def localize(
        self,
        line: ArrayLike,
        sample: ArrayLike,
        h_m: ArrayLike,
        *,
        outside: Outside = "raise",
        domain: Domain = "advice",
        tolerance_px: float = 1e-9,
        max_iterations: int = 30,
    ) -> tuple[FloatArray, FloatArray]:
        """Image point at a height -> ground (the inverse of :meth:`project` at fixed h).

        Newton iteration on (L, P) with the analytic Jacobian, started from the linear terms.

        Args:
            line: line, pixels (this project's convention), any shape (broadcast).
            sample: sample, pixels.
            h_m: height above the WGS84 ellipsoid, metres.
            outside: for points that fail (not converged to 1e-6 px; with ``domain ==
                "limit"`` also inputs outside the domain, normalized line, sample or height
                beyond 1.1, and solutions outside it): ``"raise"``, ``"nan"`` or ``"ignore"``
                (return the best iterate).
            domain: ``"advice"`` (default: solve wherever asked, as GDAL does) or ``"limit"``.
            tolerance_px: a point stops iterating when its re-projection error is below this,
                pixels (or stops decreasing: float64 evaluation of the polynomials is good to
                about 1e-9 px on a 40000 px scene).
            max_iterations: Newton iterations at most.

        Returns:
            (lon, lat), degrees (WGS84), the broadcast shape; re-projected at ``h_m`` they give
            (line, sample) to better than 1e-6 px (tolerance_px when reachable in float64).

        Raises:
            RPCDomainError: input or solution outside a limiting domain (``outside ==
                "raise"``).
            RPCConvergenceError: not converged to 1e-6 px (``outside == "raise"``).

        """
        li, sa, hh = np.broadcast_arrays(
            np.asarray(line, dtype=np.float64),
            np.asarray(sample, dtype=np.float64),
            np.asarray(h_m, dtype=np.float64),
        )
        ln = (li - self.line_off) / self.line_scale
        sn = (sa - self.samp_off) / self.samp_scale
        H = (hh - self.height_off) / self.height_scale
        with np.errstate(invalid="ignore"):
            bad_in = ~((np.abs(ln) <= _LIMIT) & (np.abs(sn) <= _LIMIT) & (np.abs(H) <= _LIMIT))
        if domain != "limit":
            bad_in = ~(np.isfinite(ln) & np.isfinite(sn) & np.isfinite(H))
        _handle(bad_in, outside, RPCDomainError, "(line, sample, h) are outside the domain")
        # Start: the linear part of the numerators (denominators ~ 1), solved for L, P.
        a, b = self.line_num_coeff, self.samp_num_coeff
        det0 = a[1] * b[2] - a[2] * b[1]
        if det0 == 0.0:
            L = np.zeros_like(ln)
            P = np.zeros_like(ln)
        else:
            rl = ln - a[0] - a[3] * H
            rs = sn - b[0] - b[3] * H
            L = (rl * b[2] - rs * a[2]) / det0
            P = (a[1] * rs - b[1] * rl) / det0
        err = np.full(ln.shape, np.inf)  # re-projection error of the best iterate, px
        best_l, best_p = L, P
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            for k in range(max_iterations + 1):
                _, num, den = self._ratios(L, P, H)
                f = num / den
                rl = (f[..., 0] - ln) * self.line_scale
                rs = (f[..., 1] - sn) * self.samp_scale
                e = np.hypot(rl, rs)
                better = e < err
                best_l = np.where(better, L, best_l)
                best_p = np.where(better, P, best_p)
                err = np.where(better, e, err)
                # Go on where the last step helped and the tolerance is not met; a point whose
                # error stopped decreasing has reached float64's noise floor (about 1e-9 px).
                active = better & (e > tolerance_px)
                if k == max_iterations or not np.any(active):
                    break
                tl = _terms_dl(L, P, H)
                tp = _terms_dp(L, P, H)
                dfl = ((tl @ self._num) - f * (tl @ self._den)) / den
                dfp = ((tp @ self._num) - f * (tp @ self._den)) / den
                j11 = dfl[..., 0] * self.line_scale
                j12 = dfp[..., 0] * self.line_scale
                j21 = dfl[..., 1] * self.samp_scale
                j22 = dfp[..., 1] * self.samp_scale
                det = j11 * j22 - j12 * j21
                L = np.where(active, L - (j22 * rl - j12 * rs) / det, L)
                P = np.where(active, P - (j11 * rs - j21 * rl) / det, P)
        L, P = best_l, best_p
        bad_conv = ~(err < 1e-6)
        with np.errstate(invalid="ignore"):
            bad_out = ~((np.abs(L) <= _LIMIT) & (np.abs(P) <= _LIMIT))
        if domain != "limit":
            bad_out = np.zeros(L.shape, dtype=bool)
        _handle(bad_conv & ~bad_in, outside, RPCConvergenceError, "did not converge to 1e-6 px")
        _handle(bad_out & ~bad_in, outside, RPCDomainError, "localize outside the domain")
        lon = L * self.long_scale + self.long_off
        lat = P * self.lat_scale + self.lat_off
        if outside == "nan":
            bad = bad_in | bad_conv | bad_out
            lon = np.where(bad, np.nan, lon)
            lat = np.where(bad, np.nan, lat)
        return np.asarray(lon, dtype=np.float64), np.asarray(lat, dtype=np.float64)


_SCALARS: tuple[str, ...] = (
    "line_off", "samp_off", "lat_off", "long_off", "height_off",
    "line_scale", "samp_scale", "lat_scale", "long_scale", "height_scale",
)  # fmt: skip
_COEFF_NAMES: tuple[str, ...] = (
    "line_num_coeff", "line_den_coeff", "samp_num_coeff", "samp_den_coeff",
)  # fmt: skip


def _model(
    scalars: dict[str, float],
    coeffs: dict[str, FloatArray],
    source: str | Path | None = None,
    **extra: float,
) -> RPCModel:
    where = f"{source}: " if source is not None else ""
    missing = [n for n in _SCALARS if n not in scalars] + [
        n for n in _COEFF_NAMES if n not in coeffs
    ]
    if missing:
        raise RPCFormatError(f"{where}missing RPC values: {', '.join(missing)}")
    kwargs: dict[str, float] = {n: scalars[n] for n in _SCALARS}
    try:
        return RPCModel(**kwargs, **coeffs, **extra)  # type: ignore[arg-type]
    except RPCFormatError as err:
        raise RPCFormatError(f"{where}{err}") from None


_NUMBER = re.compile(
    r"\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eEdD][-+]?\d+)?)"
    r"(?:\s+(?:pixels?|meters?|metres?|degrees?|deg|m))?\s*;?\s*",
    re.IGNORECASE,
)


def _float(text: str, what: str, source: str | Path | None = None) -> float:
    """A number as RPC files write it, or an error naming file, key and value.

    Optional sign, decimals, exponent (E or Fortran D), optionally a unit (``+021109.50
    pixels``: pixels, meters, metres, degrees). Anything else (``1,5``, ``12abc3``, two
    numbers) is an error naming the file, the key and the value: never a partial read.
    """
    m = _NUMBER.fullmatch(text)
    if m is None:
        where = f"{source}: " if source is not None else ""
        raise RPCFormatError(
            f"{where}{what}: not a number: {text.strip()[:40]!r} (a decimal point is needed, "
            "e.g. 1.5, not 1,5)"
        )
    return float(m.group(1).replace("d", "e").replace("D", "E"))


# ---------------------------------------------------------------------------------------------
# OSSIM keyword list (.geom)


def read_keyword_list(path: str | Path) -> dict[str, str]:
    """An OSSIM keyword list (``key: value`` lines) as a dict of stripped strings."""
    out: dict[str, str] = {}
    for raw in Path(path).read_text(encoding="utf-8", errors="replace").splitlines():
        key, sep, value = raw.partition(":")
        if sep and key.strip():
            out[key.strip()] = value.strip()
    return out


def read_geom(path: str | Path) -> RPCModel:
    """Read an OSSIM ``.geom`` keyword list with an RPC (ossimRpcModel, ossimPleiadesModel, ...).

    Keys ``line_off``, ..., ``height_scale``, ``line_num_coeff_00`` .. ``_19`` etc. (an optional
    ``prefix.`` is accepted); ``polynomial_format: A`` coefficients are reordered to RPC00B.
    OSSIM image coordinates are 0-based with pixel centres at integers: no conversion.

    Raises:
        RPCFormatError: a key is missing or malformed.

    """
    kwl = read_keyword_list(path)
    flat: dict[str, str] = {}
    for key, value in kwl.items():
        flat.setdefault(key.rsplit(".", 1)[-1].lower(), value)
    scalars = {n: _float(flat[n], n, path) for n in _SCALARS if n in flat}
    coeffs: dict[str, FloatArray] = {}
    for name in _COEFF_NAMES:
        keys = [f"{name}_{i:02d}" for i in range(20)]
        if all(k in flat for k in keys):
            coeffs[name] = np.array([_float(flat[k], k, path) for k in keys])
    if flat.get("polynomial_format", "B").strip().upper() == "A":
        coeffs = {k: v[_A_TO_B] for k, v in coeffs.items()}
    extra = {}
    if "bias_error" in flat:
        extra["err_bias"] = _float(flat["bias_error"], "bias_error", path)
    if "rand_error" in flat:
        extra["err_rand"] = _float(flat["rand_error"], "rand_error", path)
    return _model(scalars, coeffs, path, **extra)


def write_geom(
    path: str | Path, rpc: RPCModel, *, lines: int | None = None, samples: int | None = None
) -> None:
    """Write an OSSIM ``.geom`` keyword list (type ossimRpcModel, polynomial_format B).

    Values are written with Python's shortest round-trip repr, so reading gives the same bits.

    Args:
        path: output file.
        rpc: the model.
        lines: image lines (written as ``number_lines`` when given).
        samples: image samples (``number_samples``).

    """
    out = ["type:  ossimRpcModel", "polynomial_format:  B"]
    out += [f"bias_error:  {rpc.err_bias!r}", f"rand_error:  {rpc.err_rand!r}"]
    out += [f"{n}:  {getattr(rpc, n)!r}" for n in _SCALARS]
    for name in _COEFF_NAMES:
        out += [f"{name}_{i:02d}:  {float(c)!r}" for i, c in enumerate(getattr(rpc, name))]
    if lines is not None:
        out.append(f"number_lines:  {int(lines)}")
    if samples is not None:
        out.append(f"number_samples:  {int(samples)}")
    Path(path).write_text("\n".join(out) + "\n", encoding="utf-8")


# ---------------------------------------------------------------------------------------------
# _RPC.TXT (IKONOS / DigitalGlobe / GDAL text)

_TXT_SCALARS = {n.upper(): n for n in _SCALARS}
_TXT_UNITS = {
    "line_off": "pixels", "samp_off": "pixels", "lat_off": "degrees", "long_off": "degrees",
    "height_off": "meters", "line_scale": "pixels", "samp_scale": "pixels",
    "lat_scale": "degrees", "long_scale": "degrees", "height_scale": "meters",
}  # fmt: skip


def read_rpc_txt(path: str | Path) -> RPCModel:
    """Read an ``_RPC.TXT`` file (``LINE_OFF: +002000.00 pixels`` ..., coefficients 1..20).

    RPC00B convention ((0, 0) = centre of the first pixel): no conversion. ``ERR_BIAS`` and
    ``ERR_RAND`` are read when present.

    Raises:
        RPCFormatError: a value is missing or malformed.

    """
    values: dict[str, str] = {}
    for raw in Path(path).read_text(encoding="utf-8", errors="replace").splitlines():
        key, sep, value = raw.partition(":")
        if sep:
            values[key.strip().upper()] = value
    scalars = {n: _float(values[k], k, path) for k, n in _TXT_SCALARS.items() if k in values}
    coeffs: dict[str, FloatArray] = {}
    for name in _COEFF_NAMES:
        keys = [f"{name.upper()}_{i}" for i in range(1, 21)]
        if all(k in values for k in keys):
            coeffs[name] = np.array([_float(values[k], k, path) for k in keys])
    extra = {
        n: _float(values[k], k, path)
        for k, n in (("ERR_BIAS", "err_bias"), ("ERR_RAND", "err_rand"))
        if k in values
    }
    return _model(scalars, coeffs, path, **extra)


def write_rpc_txt(path: str | Path, rpc: RPCModel) -> None:
    """Write an ``_RPC.TXT`` file (17 significant digits: reading gives the same bits)."""
    out = [f"ERR_BIAS: {rpc.err_bias:+.16E} meters", f"ERR_RAND: {rpc.err_rand:+.16E} meters"]
    out += [f"{n.upper()}: {getattr(rpc, n):+.16E} {_TXT_UNITS[n]}" for n in _SCALARS]
    for name in _COEFF_NAMES:
        out += [
            f"{name.upper()}_{i + 1}: {float(c):+.16E}" for i, c in enumerate(getattr(rpc, name))
        ]
    Path(path).write_text("\n".join(out) + "\n", encoding="utf-8")


# ---------------------------------------------------------------------------------------------
# .RPB (DigitalGlobe)

_RPB_SCALARS = {
    "lineoffset": "line_off", "sampoffset": "samp_off", "latoffset": "lat_off",
    "longoffset": "long_off", "heightoffset": "height_off", "linescale": "line_scale",
    "sampscale": "samp_scale", "latscale": "lat_scale", "longscale": "long_scale",
    "heightscale": "height_scale", "errbias": "err_bias", "errrand": "err_rand",
}  # fmt: skip
_RPB_COEFFS = {
    "linenumcoef": "line_num_coeff", "linedencoef": "line_den_coeff",
    "sampnumcoef": "samp_num_coeff", "sampdencoef": "samp_den_coeff",
}  # fmt: skip


def read_rpb(path: str | Path) -> RPCModel:
    """Read a DigitalGlobe ``.RPB`` file.

    Syntax: ``BEGIN_GROUP = IMAGE``, ``lineOffset = ...;``, ``lineNumCoef = ( c1, ..., c20 );``.
    RPC00B convention: no conversion.

    Raises:
        RPCFormatError: a value is missing or malformed.

    """
    text = Path(path).read_text(encoding="utf-8", errors="replace")
    found: dict[str, float] = {}
    coeffs: dict[str, FloatArray] = {}
    for m in re.finditer(r"(\w+)\s*=\s*(\([^)]*\)|[^;\n]*)\s*;?", text):
        key, value = m.group(1).lower(), m.group(2).strip()
        if key in _RPB_COEFFS:
            items = [s for s in value.strip("()").replace("\n", " ").split(",") if s.strip()]
            coeffs[_RPB_COEFFS[key]] = np.array([_float(s, key, path) for s in items])
        elif key in _RPB_SCALARS:
            found[_RPB_SCALARS[key]] = _float(value, key, path)
    extra = {k: found.pop(k) for k in ("err_bias", "err_rand") if k in found}
    return _model(found, coeffs, path, **extra)


def write_rpb(path: str | Path, rpc: RPCModel, *, sat_id: str = "UNKNOWN") -> None:
    """Write a DigitalGlobe ``.RPB`` file (17 significant digits: reading gives the same bits)."""
    names = {v: k for k, v in _RPB_SCALARS.items()}
    camel = {
        "errbias": "errBias", "errrand": "errRand", "lineoffset": "lineOffset",
        "sampoffset": "sampOffset", "latoffset": "latOffset", "longoffset": "longOffset",
        "heightoffset": "heightOffset", "linescale": "lineScale", "sampscale": "sampScale",
        "latscale": "latScale", "longscale": "longScale", "heightscale": "heightScale",
        "linenumcoef": "lineNumCoef", "linedencoef": "lineDenCoef",
        "sampnumcoef": "sampNumCoef", "sampdencoef": "sampDenCoef",
    }  # fmt: skip
    out = [f'satId = "{sat_id}";', 'bandId = "P";', 'SpecId = "RPC00B";', "BEGIN_GROUP = IMAGE"]
    for n in ("err_bias", "err_rand", *_SCALARS):
        out.append(f"\t{camel[names[n]]} = {getattr(rpc, n):+.16E};")
    for key, name in _RPB_COEFFS.items():
        vals = ",\n".join(f"\t\t\t{float(c):+.16E}" for c in getattr(rpc, name))
        out.append(f"\t{camel[key]} = (\n{vals});")
    out += ["END_GROUP = IMAGE", "END;"]
    Path(path).write_text("\n".join(out) + "\n", encoding="utf-8")


# ---------------------------------------------------------------------------------------------
# DIMAP RPC XML (Airbus Pleiades / SPOT 6-7 / Pleiades Neo)


def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1]


def dimap_pixel_origin(path: str | Path) -> float:
    """Image coordinate of the centre of the first pixel in a DIMAP RPC file.

    DIMAP v3 (Pleiades Neo) states it as ``FIRST_COL`` of ``ImagetoGround_Validity_Domain``
    (GDAL uses that value for lines and samples alike; it is 0 for PNEO); DIMAP v2 (Pleiades
    1A/1B, SPOT 6/7) is 1-based: 1.0.
    """
    root = ET.parse(Path(path)).getroot()
    for node in root.iter():
        if _local(node.tag) == "ImagetoGround_Validity_Domain":
            for child in node:
                if _local(child.tag) == "FIRST_COL" and child.text:
                    return _float(child.text, "FIRST_COL", path)
    return 1.0


def read_dimap_rpc(path: str | Path, *, origin: float | None = None) -> RPCModel:
    """Read the ground -> image RPC of a DIMAP ``RPC_*.XML`` file.

    The coefficients are those of ``Inverse_Model`` (DIMAP v2) or ``GroundtoImage_Values``
    (v3), RPC00B order; offsets and scales from ``RFM_Validity``. The image coordinates are
    converted to this project's convention by subtracting ``origin`` from LINE_OFF and SAMP_OFF.

    Args:
        path: the XML file.
        origin: image coordinate of the centre of the first pixel in the file; None = detect
            (:func:`dimap_pixel_origin`: 1 for DIMAP v2); 0.0 returns the file's raw values.

    Raises:
        RPCFormatError: not a DIMAP RPC file, or a value is missing.

    """
    try:
        root = ET.parse(Path(path)).getroot()
    except ET.ParseError as exc:
        raise RPCFormatError(f"{path}: not XML ({exc})") from exc
    model = None
    for node in root.iter():
        if _local(node.tag) in ("Inverse_Model", "GroundtoImage_Values"):
            model = node
            break
    if model is None:
        raise RPCFormatError(f"{path}: no Inverse_Model / GroundtoImage_Values element")
    values = {_local(c.tag).upper(): (c.text or "") for c in model}
    coeffs: dict[str, FloatArray] = {}
    for name in _COEFF_NAMES:
        keys = [f"{name.upper()}_{i}" for i in range(1, 21)]
        if all(k in values for k in keys):
            coeffs[name] = np.array([_float(values[k], k, path) for k in keys])
    scalars: dict[str, float] = {}
    for node in root.iter():
        tag = _local(node.tag).upper()
        if tag in _TXT_SCALARS and node.text and _TXT_SCALARS[tag] not in scalars:
            scalars[_TXT_SCALARS[tag]] = _float(node.text, tag, path)
    shift = dimap_pixel_origin(path) if origin is None else float(origin)
    if "line_off" in scalars:
        scalars["line_off"] -= shift
    if "samp_off" in scalars:
        scalars["samp_off"] -= shift
    return _model(scalars, coeffs, path)


def write_dimap_rpc(path: str | Path, rpc: RPCModel) -> None:
    """Write a minimal DIMAP v2 RPC XML (Inverse_Model and RFM_Validity; 1-based offsets)."""
    root = ET.Element("Dimap_Document")
    ident = ET.SubElement(root, "Metadata_Identification")
    ET.SubElement(ident, "METADATA_FORMAT", version="2.0").text = "DIMAP"
    ET.SubElement(ident, "METADATA_SUBPROFILE").text = "RPC"
    rfm = ET.SubElement(ET.SubElement(root, "Rational_Function_Model"), "Global_RFM")
    inverse = ET.SubElement(rfm, "Inverse_Model")
    for name in ("samp_num_coeff", "samp_den_coeff", "line_num_coeff", "line_den_coeff"):
        for i, c in enumerate(getattr(rpc, name), start=1):
            ET.SubElement(inverse, f"{name.upper()}_{i}").text = repr(float(c))
    validity = ET.SubElement(rfm, "RFM_Validity")
    for n in reversed(_SCALARS):
        value = getattr(rpc, n) + (1.0 if n in ("line_off", "samp_off") else 0.0)
        ET.SubElement(validity, n.upper()).text = repr(value)
    ET.indent(root)
    ET.ElementTree(root).write(Path(path), encoding="UTF-8", xml_declaration=True)


# ---------------------------------------------------------------------------------------------
# GeoTIFF RPCCoefficientTag


def read_geotiff_rpc(path: str | Path) -> RPCModel:
    """Read the RPCCoefficientTag (50844, 92 doubles) of the first page of a (Geo)TIFF.

    RPC00B convention (GDAL writes the tag from its RPC metadata unchanged): no conversion.

    Raises:
        RPCFormatError: no such tag, or not 92 values.

    """
    import tifffile

    with tifffile.TiffFile(Path(path)) as tif:
        tag = tif.pages.first.tags.get(RPC_TIFF_TAG)
        if tag is None:
            raise RPCFormatError(f"{path}: no RPCCoefficientTag ({RPC_TIFF_TAG})")
        values = np.asarray(tag.value, dtype=np.float64).reshape(-1)
    return RPCModel.from_vector(values)


def write_geotiff_rpc(path: str | Path, rpc: RPCModel, image: ArrayLike | None = None) -> None:
    """Write a TIFF carrying the RPC in tag 50844 (DOUBLE x 92).

    Args:
        path: output file.
        rpc: the model (offsets in this project's convention = RPC00B).
        image: pixels to store (default a 1 x 1 uint8 placeholder).

    """
    import tifffile

    data = np.zeros((1, 1), np.uint8) if image is None else np.asarray(image)
    vec = tuple(float(v) for v in rpc.as_vector())
    tifffile.imwrite(Path(path), data, extratags=[(RPC_TIFF_TAG, 12, 92, vec, True)])


# ---------------------------------------------------------------------------------------------
# Dispatch

RPCFormat = Literal["geom", "rpc_txt", "rpb", "dimap", "geotiff"]


def detect_rpc_format(path: str | Path) -> RPCFormat:
    """Which RPC format a file holds, from its content (the extension only breaks ties).

    Raises:
        RPCFormatError: none of the known formats.

    """
    p = Path(path)
    head = p.read_bytes()[:4096]
    if head[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return "geotiff"
    text = head.decode("utf-8", errors="replace")
    if text.lstrip().startswith("<") or "Dimap_Document" in text:
        return "dimap"
    if re.search(r"BEGIN_GROUP|lineNumCoef|lineOffset\s*=", text, re.IGNORECASE):
        return "rpb"
    full = p.read_text(encoding="utf-8", errors="replace")
    if re.search(r"^\s*([\w.]*\.)?line_num_coeff_00\s*:", full, re.IGNORECASE | re.MULTILINE):
        return "geom"
    if re.search(r"^\s*LINE_NUM_COEFF_1\s*:", full, re.IGNORECASE | re.MULTILINE):
        return "rpc_txt"
    ext = p.suffix.lower()
    by_ext: dict[str, RPCFormat] = {
        ".geom": "geom",
        ".rpb": "rpb",
        ".xml": "dimap",
        ".tif": "geotiff",
        ".tiff": "geotiff",
    }
    if ext in by_ext:
        return by_ext[ext]
    raise RPCFormatError(f"{p}: not a known RPC format (.geom, _RPC.TXT, .RPB, DIMAP, GeoTIFF)")


def read_rpc(path: str | Path) -> RPCModel:
    """Read an RPC from any supported format (:func:`detect_rpc_format`).

    The returned model is in this project's pixel convention (module docstring).
    """
    readers: dict[RPCFormat, Callable[[str | Path], RPCModel]] = {
        "geom": read_geom,
        "rpc_txt": read_rpc_txt,
        "rpb": read_rpb,
        "dimap": read_dimap_rpc,
        "geotiff": read_geotiff_rpc,
    }
    return readers[detect_rpc_format(path)](path)


# ---------------------------------------------------------------------------------------------
# Geodetic, ECEF, local tangent plane (WGS84)


def ecef_from_geodetic(
    lon_deg: ArrayLike, lat_deg: ArrayLike, h_m: ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """WGS84 geodetic (lon, lat degrees; h metres above the ellipsoid) -> ECEF X, Y, Z metres."""
    lon, lat, h = np.broadcast_arrays(
        np.radians(np.asarray(lon_deg, dtype=np.float64)),
        np.radians(np.asarray(lat_deg, dtype=np.float64)),
        np.asarray(h_m, dtype=np.float64),
    )
    s, c = np.sin(lat), np.cos(lat)
    n = WGS84_A / np.sqrt(1.0 - _E2 * s * s)
    return (
        (n + h) * c * np.cos(lon),
        (n + h) * c * np.sin(lon),
        (n * (1.0 - _E2) + h) * s,
    )


def geodetic_from_ecef(
    x: ArrayLike, y: ArrayLike, z: ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """ECEF X, Y, Z metres -> WGS84 (lon deg, lat deg, h metres above the ellipsoid).

    Bowring's iteration on the parametric latitude, four rounds: errors below 1e-13 deg and 1e-7 m
    from 6000 km below the surface out to geostationary distances (undefined at the centre).
    """
    xb, yb, zb = np.broadcast_arrays(
        np.asarray(x, dtype=np.float64),
        np.asarray(y, dtype=np.float64),
        np.asarray(z, dtype=np.float64),
    )
    p = np.hypot(xb, yb)
    beta = np.arctan2(zb, (1.0 - WGS84_F) * p)
    for _ in range(4):
        lat = np.arctan2(zb + _EP2 * _B * np.sin(beta) ** 3, p - _E2 * WGS84_A * np.cos(beta) ** 3)
        beta = np.arctan2((1.0 - WGS84_F) * np.sin(lat), np.cos(lat))
    lat = np.arctan2(zb + _EP2 * _B * np.sin(beta) ** 3, p - _E2 * WGS84_A * np.cos(beta) ** 3)
    s = np.sin(lat)
    h = p * np.cos(lat) + zb * s - WGS84_A * np.sqrt(1.0 - _E2 * s * s)
    return np.degrees(np.arctan2(yb, xb)), np.degrees(lat), h


@dataclass(frozen=True)
class LocalTangentPlane:
    """A local east-north-up Cartesian frame on WGS84 (the object frame, Z up, metres).

    Origin at geodetic (lat0, lon0, h0); X east, Y north, Z along the ellipsoid normal at the
    origin. Exact (a rotation and a translation of ECEF).

    Attributes:
        lat0: origin latitude, degrees.
        lon0: origin longitude, degrees.
        h0: origin height above the WGS84 ellipsoid, metres.

    """

    lat0: float
    lon0: float
    h0: float = 0.0
    origin_ecef: FloatArray = field(init=False, repr=False)
    rotation: FloatArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        for name in ("lat0", "lon0", "h0"):
            object.__setattr__(self, name, float(getattr(self, name)))
        if not (-90.0 <= self.lat0 <= 90.0 and math.isfinite(self.lon0 + self.h0)):
            raise ValueError(f"bad origin ({self.lat0}, {self.lon0}, {self.h0})")
        o = np.array([float(v) for v in ecef_from_geodetic(self.lon0, self.lat0, self.h0)])
        lat, lon = math.radians(self.lat0), math.radians(self.lon0)
        sl, cl, sp, cp = math.sin(lon), math.cos(lon), math.sin(lat), math.cos(lat)
        r = np.array([[-sl, cl, 0.0], [-sp * cl, -sp * sl, cp], [cp * cl, cp * sl, sp]])
        o.setflags(write=False)
        r.setflags(write=False)
        object.__setattr__(self, "origin_ecef", o)
        object.__setattr__(self, "rotation", r)  # rows: east, north, up in ECEF

    def to_local(
        self, lon_deg: ArrayLike, lat_deg: ArrayLike, h_m: ArrayLike
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Geodetic (lon deg, lat deg, h m ellipsoidal) -> (X east, Y north, Z up), metres."""
        x, y, z = ecef_from_geodetic(lon_deg, lat_deg, h_m)
        d = np.stack([x, y, z], axis=-1) - self.origin_ecef
        e = d @ self.rotation.T
        return e[..., 0], e[..., 1], e[..., 2]

    def to_geodetic(
        self, x: ArrayLike, y: ArrayLike, z: ArrayLike
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(X east, Y north, Z up) metres -> geodetic (lon deg, lat deg, h m ellipsoidal)."""
        xb, yb, zb = np.broadcast_arrays(
            np.asarray(x, dtype=np.float64),
            np.asarray(y, dtype=np.float64),
            np.asarray(z, dtype=np.float64),
        )
        ecef = np.stack([xb, yb, zb], axis=-1) @ self.rotation + self.origin_ecef
        return geodetic_from_ecef(ecef[..., 0], ecef[..., 1], ecef[..., 2])


# ---------------------------------------------------------------------------------------------
# DEM


def grid_height(
    heights: ArrayLike,
    *,
    lat_max: float,
    lon_min: float,
    step_deg: float,
    geoid_undulation: float = 0.0,
) -> HeightFunction:
    """A height function from a regular latitude/longitude grid (bilinear; NaN outside).

    Grid node (row i, column j) is at latitude ``lat_max - i * step_deg`` and longitude
    ``lon_min + j * step_deg`` (row 0 north; nodes are point samples, as in SRTM tiles, whose
    edge rows and columns lie on whole degrees).

    Args:
        heights: (rows, columns) heights, metres, at least 2 x 2.
        lat_max: latitude of row 0, degrees.
        lon_min: longitude of column 0, degrees.
        step_deg: node spacing in latitude and longitude, degrees.
        geoid_undulation: N added to every height, metres (geoid -> WGS84 ellipsoid).

    Returns:
        ``height(lon_deg, lat_deg) -> h`` (metres), broadcast shape; NaN outside the grid.

    """
    data = np.array(heights, dtype=np.float64)
    if data.ndim != 2 or min(data.shape) < 2 or not np.all(np.isfinite(data)):
        raise ValueError(f"heights must be a finite 2-D grid of at least 2 x 2, got {data.shape}")
    if not step_deg > 0:
        raise ValueError(f"step_deg must be > 0, got {step_deg}")
    nr, nc = data.shape
    undulation = float(geoid_undulation)

    def height(lon: FloatArray, lat: FloatArray) -> FloatArray:
        lo, la = np.broadcast_arrays(np.asarray(lon, float), np.asarray(lat, float))
        r = (lat_max - la) / step_deg
        c = (lo - lon_min) / step_deg
        with np.errstate(invalid="ignore"):
            inside = (r >= 0) & (r <= nr - 1) & (c >= 0) & (c <= nc - 1)
        rc = np.clip(np.nan_to_num(r), 0, nr - 1)
        cc = np.clip(np.nan_to_num(c), 0, nc - 1)
        i = np.minimum(rc.astype(np.intp), nr - 2)
        j = np.minimum(cc.astype(np.intp), nc - 2)
        tr, tc = rc - i, cc - j
        top = data[i, j] + tc * (data[i, j + 1] - data[i, j])
        bottom = data[i + 1, j] + tc * (data[i + 1, j + 1] - data[i + 1, j])
        h = top + tr * (bottom - top) + undulation
        return np.asarray(np.where(inside, h, np.nan), dtype=np.float64)

    return height


def srtm_height(
    path: str | Path,
    *,
    geoid_undulation: float = 0.0,
    tile_origin: tuple[float, float] | None = None,
) -> HeightFunction:
    """An SRTM ``.hgt`` tile as a height function (bilinear; NaN outside the tile).

    SRTM heights are above the EGM96 geoid. The RPC needs ellipsoidal heights: h = H + N. N (the
    geoid undulation, metres) is ignored unless supplied, as a constant: at Mont Ventoux it is
    about 50 m, and it varies by a few metres over a scene, which matters little for virtual GCP
    (they are spread over a height range anyway) but must be given for absolute heights.

    Args:
        path: 1201^2 (3") or 3601^2 (1") tile (voids filled by their nearest neighbour, see
            :func:`parproj_ros.imaging.terrain.read_hgt`).
        geoid_undulation: N added to every height, metres.
        tile_origin: (lat, lon) of the SW corner, degrees (default: from the name N44E005).

    Returns:
        ``height(lon_deg, lat_deg) -> h`` (metres), broadcast shape.

    """
    from .imaging.terrain import _tile_origin, read_hgt

    p = Path(path)
    lat_sw, lon_sw = tile_origin if tile_origin is not None else _tile_origin(p)
    data = read_hgt(p)
    return grid_height(
        data,
        lat_max=lat_sw + 1.0,
        lon_min=lon_sw,
        step_deg=1.0 / (data.shape[0] - 1),
        geoid_undulation=geoid_undulation,
    )


# ---------------------------------------------------------------------------------------------
# Virtual GCP


@dataclass(frozen=True)
class VirtualGCP:
    """Virtual ground control points of a stereo pair (from :func:`virtual_gcp`).

    Attributes:
        points: (n, 3) object coordinates in ``frame`` (X east, Y north, Z up), metres.
        left: (n, 2) (line, sample) in the left scene, pixels (this project's convention):
            exactly ``left_rpc.project(*geodetic.T)``.
        right: (n, 2) (line, sample) in the right scene, pixels.
        geodetic: (n, 3) (lon deg, lat deg, h m above the WGS84 ellipsoid).
        frame: the local tangent plane of ``points``.

    """

    points: FloatArray
    left: FloatArray
    right: FloatArray
    geodetic: FloatArray
    frame: LocalTangentPlane

    def __len__(self) -> int:
        return len(self.points)


def _dem_heights(
    rpc: RPCModel, line: FloatArray, sample: FloatArray, dem: HeightFunction
) -> FloatArray:
    """Height where each image ray meets the DEM (fixed point h = dem(localize(h)))."""
    h = np.full(line.shape, rpc.height_off)
    lo = rpc.height_off - DOMAIN_LIMIT * abs(rpc.height_scale)
    hi = rpc.height_off + DOMAIN_LIMIT * abs(rpc.height_scale)
    for _ in range(30):
        lon, lat = rpc.localize(line, sample, h, outside="nan", domain="limit")
        new = np.clip(np.asarray(dem(lon, lat), dtype=np.float64), lo, hi)
        with np.errstate(invalid="ignore"):
            done = np.all(~(np.abs(new - h) > 1e-3))
        h = new
        if done:
            break
    return h


def virtual_gcp(
    left: RPCModel,
    right: RPCModel,
    *,
    lines: tuple[int, int],
    samples: tuple[int, int],
    heights: tuple[float, float] | HeightFunction,
    grid: tuple[int, int, int] = (11, 11, 5),
    frame: LocalTangentPlane | None = None,
    window: tuple[float, float, float, float] | None = None,
    dem_margin: float = 100.0,
) -> VirtualGCP:
    """Virtual GCP of a pair on a 3-D grid over the left scene (paper 2's experiment).

    A regular grid of (line, sample) over ``window`` of the left image is localized at ``nz``
    heights: evenly from hmin to hmax, or, with a DEM, from DEM - dem_margin to DEM + dem_margin
    (the height where each ray meets the DEM; nz = 1: on the DEM). The ground points are
    projected into both scenes; those inside both images (pixel centres between 0 and size - 1)
    and in both validity domains are kept.

    Args:
        left: RPC of the left scene.
        right: RPC of the right scene.
        lines: number of lines of the (left, right) image.
        samples: number of samples of the (left, right) image.
        heights: (hmin, hmax) metres above the WGS84 ellipsoid, or a DEM function
            ``(lon deg, lat deg) -> ellipsoidal height m`` (e.g. :func:`srtm_height`).
        grid: (nx, ny, nz): grid points across (samples), along (lines), in height.
        frame: object frame; default: tangent plane at the kept points' mean lon, lat, height.
        window: (first_line, first_sample, last_line, last_sample) of the left image to cover;
            default the whole image.
        dem_margin: half height range about the DEM, metres.

    Returns:
        The points, their image coordinates in both scenes, geodetic coordinates and frame.

    Raises:
        RPCError: no point falls inside both scenes; bad arguments.

    """
    nx, ny, nz = (int(v) for v in grid)
    if nx < 1 or ny < 1 or nz < 1:
        raise RPCError(f"grid sizes must be >= 1, got {grid}")
    if window is None:
        window = (0.0, 0.0, lines[0] - 1.0, samples[0] - 1.0)
    l0, s0, l1, s1 = (float(v) for v in window)
    grid_l, grid_s = np.meshgrid(np.linspace(l0, l1, ny), np.linspace(s0, s1, nx), indexing="ij")
    gl, gs = grid_l.ravel(), grid_s.ravel()
    if callable(heights):
        h_dem = _dem_heights(left, gl, gs, heights)
        offsets = np.linspace(-dem_margin, dem_margin, nz) if nz > 1 else np.zeros(1)
        hh = h_dem[:, None] + offsets[None, :]
    else:
        hmin, hmax = (float(v) for v in heights)
        hh = np.broadcast_to(np.linspace(hmin, hmax, nz), (len(gl), nz))
    ll = np.repeat(gl, nz)
    ss = np.repeat(gs, nz)
    hh = hh.ravel()
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(hh)
    ll, ss, hh = ll[ok], ss[ok], hh[ok]
    lon, lat = left.localize(ll, ss, hh, outside="nan", domain="limit")
    ok = np.isfinite(lon) & np.isfinite(lat)
    lon, lat, hh = lon[ok], lat[ok], hh[ok]
    left_ls = np.stack(left.project(lon, lat, hh, outside="nan", domain="limit"), axis=-1)
    right_ls = np.stack(right.project(lon, lat, hh, outside="nan", domain="limit"), axis=-1)
    with np.errstate(invalid="ignore"):
        keep = (
            np.all(np.isfinite(left_ls), axis=1)
            & np.all(np.isfinite(right_ls), axis=1)
            & (left_ls[:, 0] >= 0) & (left_ls[:, 0] <= lines[0] - 1)
            & (left_ls[:, 1] >= 0) & (left_ls[:, 1] <= samples[0] - 1)
            & (right_ls[:, 0] >= 0) & (right_ls[:, 0] <= lines[1] - 1)
            & (right_ls[:, 1] >= 0) & (right_ls[:, 1] <= samples[1] - 1)
        )  # fmt: skip
    if not np.any(keep):
        raise RPCError("no virtual GCP falls inside both scenes: check the window and heights")
    geo = np.stack([lon[keep], lat[keep], hh[keep]], axis=-1)
    if frame is None:
        frame = LocalTangentPlane(
            float(geo[:, 1].mean()), float(geo[:, 0].mean()), float(geo[:, 2].mean())
        )
    pts = np.stack(frame.to_local(geo[:, 0], geo[:, 1], geo[:, 2]), axis=-1)
    return VirtualGCP(
        points=pts, left=left_ls[keep], right=right_ls[keep], geodetic=geo, frame=frame
    )


def estimate_scene(
    gcp: VirtualGCP,
    scene: Literal["left", "right"],
    *,
    principal_distance: float,
    pixel_size: float,
    principal_point: float,
    line_mid: float | None = None,
    psi: float | None = None,
) -> tuple[AffineEstimate, SceneFrame]:
    """Parallel projection parameters of one scene fitted to virtual GCP (paper 1 Eq 8).

    Scene coordinates: ``x = (line - line_mid) * pixel_size`` (one line = one pixel along track;
    the affine absorbs the real along-track scale), ``y = (sample - principal_point) *
    pixel_size``, metres. With psi estimated, sigma0 in pixels does not depend on the choice of
    pixel_size against principal_distance (only psi does).

    Args:
        gcp: virtual GCP.
        scene: which scene's image coordinates to fit.
        principal_distance: c, metres (Pleiades: 12.905 m).
        pixel_size: metres per pixel in the focal plane (Pleiades: 13e-6 m).
        principal_point: sample of the principal point, pixels (e.g. the line centre).
        line_mid: origin line; default the middle of the points' lines.
        psi: None to estimate the roll (Eq 8); radians to hold it; 0.0 for no PTP.

    Returns:
        The estimate (sigma0 in metres and pixels, residuals) and the scene frame used.

    """
    ls = gcp.left if scene == "left" else gcp.right
    if line_mid is None:
        line_mid = 0.5 * float(ls[:, 0].min() + ls[:, 0].max())
    frame = SceneFrame(
        line_mid=float(line_mid),
        x_per_line=float(pixel_size),
        pixel_size=float(pixel_size),
        principal_point=float(principal_point),
    )
    xy = frame.to_scene(ls[:, 0], ls[:, 1])
    est = estimate_affine(
        gcp.points, xy, principal_distance=principal_distance, pixel_size=pixel_size, psi=psi
    )
    return est, frame
