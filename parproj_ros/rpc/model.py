"""The RPC model (NITF RPC00B): ground <-> image, normalization, validity domain, errors.

Conventions: see :mod:`parproj_ros.rpc`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

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


_SCALARS: tuple[str, ...] = (
    "line_off", "samp_off", "lat_off", "long_off", "height_off",
    "line_scale", "samp_scale", "lat_scale", "long_scale", "height_scale",
)  # fmt: skip
_COEFF_NAMES: tuple[str, ...] = (
    "line_num_coeff", "line_den_coeff", "samp_num_coeff", "samp_den_coeff",
)  # fmt: skip


# ---------------------------------------------------------------------------------------------
# The model

#: Ground heights an RPC may span, metres from the ellipsoid (no ground lies 100 km away:
#: a larger height_off or height_scale is a damaged RPC; 1e9 made every other image's check
#: fail at the default heights, height_off +- height_scale / 2 of the first image).
MAX_GROUND_HEIGHT_M = 1.0e5


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
        if abs(self.height_off) + abs(self.height_scale) > MAX_GROUND_HEIGHT_M:
            raise RPCFormatError(
                f"height_off {self.height_off:g} m +- height_scale {self.height_scale:g} m "
                f"reaches beyond {MAX_GROUND_HEIGHT_M:g} m from the ellipsoid: an RPC's "
                "heights are the ground's"
            )
        for name, limit in (("lat_off", 90.0), ("long_off", 360.0)):
            if abs(getattr(self, name)) > limit:
                raise RPCFormatError(
                    f"{name} must be within +-{limit:g} deg, got {getattr(self, name):g}"
                )
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

    def linear_ground(
        self, line: ArrayLike, sample: ArrayLike, h_m: ArrayLike
    ) -> tuple[FloatArray, FloatArray]:
        """Ground of image points by the numerators' linear terms alone (denominators taken as 1).

        The start of :meth:`localize`'s Newton iteration: a rough footprint (lon, lat degrees)
        that needs no convergence, so it also exists where the full model fails.
        """
        ln, sn, H = self._normalized_image(line, sample, h_m)
        L, P = self._linear_start(ln, sn, H)
        return L * self.long_scale + self.long_off, P * self.lat_scale + self.lat_off

    def _normalized_image(
        self, line: ArrayLike, sample: ArrayLike, h_m: ArrayLike
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Image points and heights in the model's normalized units (broadcast, float64)."""
        li, sa, hh = np.broadcast_arrays(
            np.asarray(line, dtype=np.float64),
            np.asarray(sample, dtype=np.float64),
            np.asarray(h_m, dtype=np.float64),
        )
        return (
            (li - self.line_off) / self.line_scale,
            (sa - self.samp_off) / self.samp_scale,
            (hh - self.height_off) / self.height_scale,
        )

    def _linear_start(
        self, ln: FloatArray, sn: FloatArray, H: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """Normalized (L, P) solving the numerators' linear part for normalized line, sample."""
        a, b = self.line_num_coeff, self.samp_num_coeff
        det0 = a[1] * b[2] - a[2] * b[1]
        if det0 == 0.0:
            return np.zeros_like(ln), np.zeros_like(ln)
        rl = ln - a[0] - a[3] * H
        rs = sn - b[0] - b[3] * H
        return (rl * b[2] - rs * a[2]) / det0, (a[1] * rs - b[1] * rl) / det0

    def image_denominator_check(
        self, line: ArrayLike, sample: ArrayLike, h_m: ArrayLike, *, lattice: int = 41
    ) -> str | None:
        """Why a denominator makes the model unusable over an image, with where; or None.

        ``line``, ``sample``, ``h_m`` (pixels, metres; broadcast) are test points spread over the
        image and its heights. The ground they cover is the lon/lat box of their ground by the
        numerators' linear terms (:meth:`linear_ground`, which needs no convergence), widened by
        the points that localize within that box's own size of it (a far branch of a broken
        model does not count); both denominators are evaluated on a ``lattice`` x ``lattice``
        grid over the box at each test height. A denominator whose coefficients are all zero, one
        that changes sign over the box or comes within 1e-6 of zero (relative to its largest
        magnitude) is reported with the ground point nearest its zero and the test point of the
        image nearest to that (a projection through such a model passes through infinity, so
        localization fails or lands on the wrong branch there).
        """
        li, sa, hh = np.broadcast_arrays(
            np.asarray(line, dtype=np.float64),
            np.asarray(sample, dtype=np.float64),
            np.asarray(h_m, dtype=np.float64),
        )
        li, sa, hh = li.ravel(), sa.ravel(), hh.ravel()
        for name, coeff in (("line", self.line_den_coeff), ("sample", self.samp_den_coeff)):
            if not np.any(coeff):
                key = "LINE_DEN_COEFF" if name == "line" else "SAMP_DEN_COEFF"
                return f"RPC {name} denominator zero everywhere (its 20 {key} are all 0)"
        with np.errstate(all="ignore"):
            lon0, lat0 = self.linear_ground(li, sa, hh)
            lon1, lat1 = self.localize(li, sa, hh, outside="nan")
        ok0 = np.isfinite(lon0) & np.isfinite(lat0)
        if not ok0.any():
            return None
        # converged points widen the box where the linear terms are rough, but a far branch
        # of a broken model (beyond the linear footprint by more than its size) does not
        box = [(float(v[ok0].min()), float(v[ok0].max())) for v in (lon0, lat0)]
        with np.errstate(invalid="ignore"):
            ok1 = np.ones(lon1.shape, dtype=bool)
            for v, (lo, hi) in zip((lon1, lat1), box, strict=True):
                ok1 &= (v >= 2 * lo - hi) & (v <= 2 * hi - lo)
        lon = np.concatenate([lon0, lon1])
        lat = np.concatenate([lat0, lat1])
        ok = np.concatenate([ok0, ok1])
        heights = np.unique(hh[np.isfinite(hh)])
        if heights.size == 0:
            return None
        g_lon, g_lat, g_h = np.meshgrid(
            np.linspace(lon[ok].min(), lon[ok].max(), lattice),
            np.linspace(lat[ok].min(), lat[ok].max(), lattice),
            heights,
            indexing="ij",
        )
        g_lon, g_lat, g_h = g_lon.ravel(), g_lat.ravel(), g_h.ravel()
        for name, d in zip(("line", "sample"), self.denominators(g_lon, g_lat, g_h), strict=True):
            good = np.isfinite(d)
            if not good.any():
                continue
            dg = d[good]
            big = float(np.abs(dg).max())
            tiny = float(np.abs(dg).min()) <= 1e-6 * big
            if not (dg.min() < 0.0 < dg.max() or tiny):
                continue
            k = int(np.flatnonzero(good)[np.argmin(np.abs(dg))])
            # the image test point whose ground (linear or localized) is nearest that zero
            src = np.concatenate([np.arange(li.size), np.arange(li.size)])
            dist = np.hypot(lon - g_lon[k], lat - g_lat[k])
            dist[~ok] = np.inf
            j = int(src[int(np.argmin(dist))])
            what = "zero" if tiny and not dg.min() < 0.0 < dg.max() else "changes sign"
            return (
                f"RPC {name} denominator {what} over the image at line {li[j]:.0f}, sample "
                f"{sa[j]:.0f}, h {hh[j]:.0f} m (lon {g_lon[k]:.6f}, lat {g_lat[k]:.6f}; "
                f"from {float(dg.min()):.3g} to {float(dg.max()):.3g} over the image's ground)"
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
        ln, sn, H = self._normalized_image(line, sample, h_m)
        with np.errstate(invalid="ignore"):
            bad_in = ~((np.abs(ln) <= _LIMIT) & (np.abs(sn) <= _LIMIT) & (np.abs(H) <= _LIMIT))
        if domain != "limit":
            bad_in = ~(np.isfinite(ln) & np.isfinite(sn) & np.isfinite(H))
        _handle(bad_in, outside, RPCDomainError, "(line, sample, h) are outside the domain")
        # Start: the linear part of the numerators (denominators ~ 1), solved for L, P.
        L, P = self._linear_start(ln, sn, H)
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
