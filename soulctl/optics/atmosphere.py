"""Atmospheric turbulence: von Kármán statistics, FFT phase screens and a frozen-flow atmosphere.

Screens are optical path difference (OPD) in nanometres, achromatic: the phase at wavelength
lambda is 2 pi OPD / lambda.  r0 is given at 500 nm (``LAMBDA_REF_M``); r0 ∝ lambda^(6/5).

Statistics (Noll 1976; Conan, Rousset & Madec 1995; Sasiela, *Electromagnetic wave propagation
in turbulence*): phase PSD at 500 nm W(k) = 0.0229 r0^(-5/3) (k^2 + 1/L0^2)^(-11/6), k in
cycles/m; its covariance and structure function in closed form with K_{5/6}.

Screens: FFT method (e.g. Schmidt, *Numerical simulation of optical wave propagation*, 2010,
ch. 9): the PSD sampled at the FFT grid frequencies.  Static screens add Lane, Glindemann &
Dainty (1992) subharmonics, 3 levels of 8 samples (as in Johansson & Gavel 1994) for the
frequencies below the grid's first one.  soulctl's choice for their weights, where W varies
fastest: each subharmonic sample carries the k^2-weighted power of its cell,
∫_cell W k^2 d^2k / k_s^2, rather than W(k_s) times the cell area; the k^2 power of the last
central cell goes to the last ring, and the k^2 power that the centre-sampled FFT cells next to
k = 0 (|i|, |j| <= 3) miss goes to the first ring.  Tilt and the structure function at
r << 1/k see the low frequencies only through that k^2 moment, so both come out right even for
Kolmogorov turbulence; focus and higher modes, which weigh the low frequencies as k^4, move by
< 0.5% on screens of 4 pupils or more (+2% for focus on 2 pupils).  With the PSD sampled at the
cell centres (Lane's weights), a 10 m Kolmogorov screen's D(r) is 10-26% low at r = 0.1-2 m;
with these weights 0.2-0.5% (both from the samples' variances).
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import numpy as np
import scipy.fft
from scipy import integrate, special

from .. import defaults
from ..errors import InputError
from ..ranges import SEEING_ARCSEC, WIND_M_S
from .interpolation import SPLINE_ORDER, UPSAMPLING, bspline_weights, fine_spline_coefficients, separable_sums

# A layer's own speed: the LBT profile's fastest layer runs at ~2.1x the effective wind, and
# every accepted effective wind (ranges.WIND_M_S) must give a valid profile.
LAYER_WIND_MAX_M_S = 300.0

LAMBDA_REF_M = 500e-9
PSD_COEFFICIENT = 0.0229  # Γ(11/6)^2 / (2 π^(11/3)) (24/5 Γ(6/5))^(5/6) = 0.022896, rounded
_KOLMOGOROV_D = 2.0 * (24.0 / 5.0 * special.gamma(6.0 / 5.0)) ** (5.0 / 6.0)  # 6.8839
_NM_PER_RAD = LAMBDA_REF_M * 1e9 / (2.0 * math.pi)  # OPD (nm) per radian of phase at 500 nm
_SUBHARMONIC_LEVELS = 3
_INNER_FFT_CELLS = 3  # the FFT cells |i|, |j| <= 3 whose k^2-power deficit the subharmonics carry
_SCREEN_CAP = 4096


def _check_positive(name: str, value: float, unit: str, allow_inf: bool = False) -> float:
    value = float(value)
    ok = value > 0 and (np.isfinite(value) or (allow_inf and value == np.inf))
    if not ok:
        rng = "> 0" + (" (inf allowed)" if allow_inf else "")
        raise InputError(f"{name} must be {rng} {unit}, got {value:g}")
    return value


def r0_from_seeing(seeing_arcsec: float) -> float:
    """Fried parameter (m) at 500 nm from the seeing FWHM (arcsec) at 500 nm."""
    return 0.98 * LAMBDA_REF_M / (seeing_arcsec / 3600.0 * math.pi / 180.0)


def r0_at_wavelength(r0_500_m: float, wavelength_m: float) -> float:
    """Fried parameter at another wavelength: r0 ∝ lambda^(6/5)."""
    r0 = _check_positive("r0", r0_500_m, "m")
    lam = _check_positive("wavelength", wavelength_m, "m")
    return r0 * (lam / LAMBDA_REF_M) ** 1.2


def phase_psd(k, r0_m: float, L0_m: float) -> np.ndarray:
    """Von Kármán phase PSD at 500 nm, rad^2 m^2, k in cycles/m (Kolmogorov for L0 = inf;
    infinite at k = 0 then)."""
    return phase_psd_k2(np.square(np.asarray(k, dtype=float)), r0_m, L0_m)


def phase_psd_k2(k2, r0_m: float, L0_m: float) -> np.ndarray:
    """``phase_psd`` of the squared spatial frequency k^2 (what 2-D grids hold)."""
    r0 = _check_positive("r0", r0_m, "m")
    L0 = _check_positive("outer scale L0", L0_m, "m", allow_inf=True)
    k2 = np.asarray(k2, dtype=float) + (0.0 if L0 == np.inf else L0**-2)
    with np.errstate(divide="ignore"):
        return PSD_COEFFICIENT * r0 ** (-5.0 / 3.0) * k2 ** (-11.0 / 6.0)


def _variance_von_karman(r0: float, L0: float) -> float:
    """C(0) = Γ(11/6) Γ(5/6) / (2 π^(8/3)) (24/5 Γ(6/5))^(5/6) (L0/r0)^(5/3)."""
    return special.gamma(11 / 6) * special.gamma(5 / 6) / (2 * math.pi ** (8 / 3)) * (_KOLMOGOROV_D / 2) * (L0 / r0) ** (5 / 3)


def phase_covariance(r, r0_m: float, L0_m: float) -> np.ndarray:
    """Von Kármán phase covariance (rad^2 at 500 nm) at separation r (m), finite L0 only:
    C(r) = C(0) 2^(1/6)/Γ(5/6) x^(5/6) K_{5/6}(x), x = 2 pi r / L0 (the Hankel transform of
    ``phase_psd``; Conan 1994 thesis, Sasiela), C(0) at r = 0."""
    r0 = _check_positive("r0", r0_m, "m")
    L0 = _check_positive("outer scale L0 (finite, for the covariance)", L0_m, "m")
    x = 2 * math.pi * np.abs(np.asarray(r, dtype=float)) / L0
    c0 = _variance_von_karman(r0, L0)
    with np.errstate(invalid="ignore", over="ignore"):
        g = 2 ** (1 / 6) / special.gamma(5 / 6) * x ** (5 / 6) * special.kv(5 / 6, x)
    return c0 * np.where(x > 0, np.nan_to_num(g, nan=0.0), 1.0)


def _one_minus_normalised_covariance(x: np.ndarray) -> np.ndarray:
    """1 - C(r)/C(0) at x = 2 pi r / L0; power series below x = 2 (no cancellation at small x):
    Γ(1/6) [ (x/2)^(5/3) Σ (x/2)^(2k)/(k! Γ(k+11/6)) - Σ_{k>=1} (x/2)^(2k)/(k! Γ(k+1/6)) ]."""
    nu = 5.0 / 6.0
    out = np.empty_like(x)
    small = x < 2.0
    h = (x[small] / 2.0) ** 2
    s_pos = np.zeros_like(h)
    s_neg = np.zeros_like(h)
    term = np.ones_like(h)
    for k in range(25):
        if k > 0:
            term = term * h / k  # (x/2)^(2k) / k!
            s_neg += term / special.gamma(k + 1 - nu)
        s_pos += term / special.gamma(k + 1 + nu)
    out[small] = special.gamma(1 - nu) * ((x[small] / 2.0) ** (2 * nu) * s_pos - s_neg)
    big = x[~small]
    out[~small] = 1.0 - 2 ** (1 / 6) / special.gamma(nu) * big**nu * special.kv(nu, big)
    return out


def structure_function(r, r0_m: float, L0_m: float) -> np.ndarray:
    """Phase structure function (rad^2 at 500 nm): 2 [C(0) - C(r)] for finite L0,
    6.88 (r/r0)^(5/3) (exactly 2 (24/5 Γ(6/5))^(5/6)) for L0 = inf."""
    r0 = _check_positive("r0", r0_m, "m")
    L0 = _check_positive("outer scale L0", L0_m, "m", allow_inf=True)
    r = np.abs(np.asarray(r, dtype=float))
    if L0 == np.inf:
        return _KOLMOGOROV_D * (r / r0) ** (5.0 / 3.0)
    x = np.atleast_1d(2 * math.pi * r / L0)
    d = 2.0 * _variance_von_karman(r0, L0) * _one_minus_normalised_covariance(x)
    return d.reshape(r.shape)


def _tilt_integral(D: float, L0: float) -> float:
    """∫_0^∞ (x^2 + a^2)^(-11/6) J2(x)^2 x^(-1) dx, a = pi D / L0 (x = pi k D)."""
    a2 = 0.0 if L0 == np.inf else (math.pi * D / L0) ** 2
    if a2 == 0.0:
        # Weber-Schafheitlin: ∫ J2(x)^2 x^(-14/3) dx, closed form.
        lam = 14.0 / 3.0
        return float(
            special.gamma(lam)
            * special.gamma(2 - lam / 2 + 0.5)
            / (2**lam * special.gamma((lam + 1) / 2) ** 2 * special.gamma(2 + lam / 2 + 0.5))
        )

    def f(x):
        return (x * x + a2) ** (-11 / 6) * special.jv(2, x) ** 2 / x

    # log-spaced below x = 1 (the integrand goes as x^3 or x^(-2/3)), half-periods above.
    total = integrate.quad(lambda u: f(math.exp(u)) * math.exp(u), math.log(1e-12), 0.0, limit=200)[0]
    edges = np.arange(1.0, 400.0, math.pi / 2)
    for lo, hi in zip(edges[:-1], edges[1:]):
        total += integrate.quad(f, lo, hi)[0]
    return total


def tilt_variance_rad2(D_m: float, r0_m: float, L0_m: float) -> float:
    """Zernike tilt variance per axis (rad^2 at 500 nm, Noll Z2 or Z3 coefficient) on a filled
    circular pupil: ∫ W(k) 16 [J2(pi k D)/(pi k D)]^2 cos^2(phi) d^2k (Noll 1976 filter;
    Conan et al. 1995) = 0.0229 * 16 pi^(8/3) (D/r0)^(5/3) ∫ (x^2+a^2)^(-11/6) J2^2/x dx.
    Kolmogorov: 0.4479 (D/r0)^(5/3), Noll's (Delta_1 - Delta_3)/2."""
    D = _check_positive("pupil diameter", D_m, "m")
    r0 = _check_positive("r0", r0_m, "m")
    L0 = _check_positive("outer scale L0", L0_m, "m", allow_inf=True)
    return PSD_COEFFICIENT * 16 * math.pi ** (8 / 3) * (D / r0) ** (5 / 3) * _tilt_integral(D, L0)


def tilt_variance_ratio(D_m: float, L0_m: float) -> float:
    """Von Kármán / Kolmogorov ratio of the Z-tilt variance on a filled pupil of diameter D
    (numerical integral of the PSD through the tilt filter): 0.137 for D = 8.2 m and
    L0 = 25 m, 0.867 for L0 = 10 km; 1 for L0 = inf."""
    D = _check_positive("pupil diameter", D_m, "m")
    L0 = _check_positive("outer scale L0", L0_m, "m", allow_inf=True)
    return _tilt_integral(D, L0) / _tilt_integral(D, np.inf)


# ----------------------------------------------------------------------------------- screens


def _cell_k2_moment(kx: np.ndarray, ky: np.ndarray, width: float, r0: float, L0: float) -> np.ndarray:
    """∫ W(k) k^2 d^2k over square cells of side ``width`` centred on (kx, ky) (midpoint rule,
    16 x 16; the cells do not contain k = 0)."""
    u = (np.arange(16) + 0.5) / 16 - 0.5
    qx = kx[:, None, None] + u[None, :, None] * width
    qy = ky[:, None, None] + u[None, None, :] * width
    q2 = qx**2 + qy**2
    return (phase_psd(np.sqrt(q2), r0, L0) * q2).mean(axis=(1, 2)) * width**2


def _central_k2_moment(half_width: float, r0: float, L0: float) -> float:
    """∫ W(k) k^2 d^2k over the square |kx|, |ky| < half_width (polar; the radial integral of
    u (u + c)^(-11/6) du/2 in closed form, c = 1/L0^2)."""
    c = 0.0 if L0 == np.inf else L0**-2
    theta = (np.arange(256) + 0.5) / 256 * (math.pi / 4)
    w_top = (half_width / np.cos(theta)) ** 2 + c

    def primitive(w):
        return 6 * w ** (1 / 6) + (1.2 * c * w ** (-5 / 6) if c > 0 else 0.0)

    radial = 0.5 * (primitive(w_top) - (primitive(c) if c > 0 else 0.0))
    return float(PSD_COEFFICIENT * r0 ** (-5 / 3) * 8 * radial.mean() * (math.pi / 4))


def _fft_variances(shape: tuple[int, int], dx: float, r0: float, L0: float) -> np.ndarray:
    """Variance (rad^2) of each FFT frequency sample of an ny x nx screen: W(k) dfy dfx, 0 at
    k = 0."""
    ny, nx = shape
    fy, fx = scipy.fft.fftfreq(ny, dx), scipy.fft.fftfreq(nx, dx)
    k2 = fy[:, None] ** 2 + fx[None, :] ** 2
    k2[0, 0] = 1.0
    var = phase_psd(np.sqrt(k2), r0, L0) * ((1.0 / (ny * dx)) * (1.0 / (nx * dx)))
    var[0, 0] = 0.0
    return var


def periodic_phase_screen(shape: tuple[int, int], pixel_scale_m: float, r0_m: float, L0_m: float, rng) -> np.ndarray:
    """An ny x nx periodic von Kármán screen, rad at 500 nm (float64): complex Gaussian
    coefficients of variance 2 W(k) dfy dfx on the FFT grid (none at k = 0), the real part of
    their inverse FFT; no power below 1/(n pixel_scale) along either axis nor above Nyquist."""
    noise = rng.standard_normal((2, *shape))
    c = noise[0] + 1j * noise[1]
    del noise  # in place from here: a long screen's set-up holds ~2 complex grids, not 4
    c *= np.sqrt(_fft_variances(shape, pixel_scale_m, r0_m, L0_m))
    return scipy.fft.ifft2(c, norm="forward", overwrite_x=True).real


def _inner_fft_k2_deficit(df: float, r0: float, L0: float) -> float:
    """k^2 power the centre-sampled FFT cells with |i|, |j| <= 3 (i, j != 0) miss:
    Σ [∫_cell W k^2 d^2k - W(k_s) df^2 k_s^2]."""
    i = np.arange(-_INNER_FFT_CELLS, _INNER_FFT_CELLS + 1)
    gi, gj = np.meshgrid(i, i)
    ring = (gi != 0) | (gj != 0)
    kx, ky = gi[ring] * df, gj[ring] * df
    k2 = kx**2 + ky**2
    return float(np.sum(_cell_k2_moment(kx, ky, df, r0, L0) - phase_psd(np.sqrt(k2), r0, L0) * df**2 * k2))


def _subharmonic_samples(n: int, dx: float, r0: float, L0: float):
    """Frequencies (kx, ky) and variances of the 3 x 8 subharmonic samples (Lane et al. 1992):
    level p splits the central cell of level p-1 into 3 x 3 cells of side df / 3^p.  Weights:
    the k^2 power of each cell over k_s^2; the last central cell's k^2 power to the last ring,
    the inner FFT cells' k^2 deficit to the first ring (module docstring)."""
    df = 1.0 / (n * dx)
    kxs, kys, vs = [], [], []
    for p in range(1, _SUBHARMONIC_LEVELS + 1):
        d = df / 3**p
        gx, gy = np.meshgrid([-d, 0.0, d], [-d, 0.0, d])
        ring = (gx != 0) | (gy != 0)
        kx, ky = gx[ring], gy[ring]
        k2 = kx**2 + ky**2
        var = _cell_k2_moment(kx, ky, d, r0, L0) / k2
        extra = 0.0
        if p == 1:
            extra += _inner_fft_k2_deficit(df, r0, L0)
        if p == _SUBHARMONIC_LEVELS:
            extra += _central_k2_moment(d / 2, r0, L0)
        # (the inner FFT cells can also carry a little too much, near k ~ 1/L0: not below 0)
        var = var * max(0.0, 1.0 + extra / np.sum(var * k2))
        kxs.append(kx)
        kys.append(ky)
        vs.append(var)
    return np.concatenate(kxs), np.concatenate(kys), np.concatenate(vs)


def fft_phase_screen(n: int, pixel_scale_m: float, r0_m: float, L0_m: float, rng, subharmonics: bool = True) -> np.ndarray:
    """An n x n von Kármán phase screen, OPD in nm (float64), r0 at 500 nm.

    FFT method: complex Gaussian coefficients of variance 2 W(k) df^2 on the FFT grid (none at
    k = 0), the real part of their inverse FFT: periodic, with no power below 1/(n pixel_scale)
    nor above the Nyquist frequency.  ``subharmonics`` adds 3 levels of Lane et al. (1992)
    subharmonics (weights in the module docstring): the screen is then not periodic and its
    piston is removed.  The FFT part uses the generator's first draws, so the same generator
    state gives the same FFT part with or without subharmonics.  ``rng``: a numpy Generator
    (or a seed for numpy.random.default_rng)."""
    if int(n) != n or n < 2:
        raise InputError(f"screen size must be an integer >= 2 pixels, got {n}")
    n = int(n)
    dx = _check_positive("pixel scale", pixel_scale_m, "m")
    r0 = _check_positive("r0", r0_m, "m")
    L0 = _check_positive("outer scale L0", L0_m, "m", allow_inf=True)
    rng = np.random.default_rng(rng)

    screen = periodic_phase_screen((n, n), dx, r0, L0, rng)
    if subharmonics:
        kx, ky, var = _subharmonic_samples(n, dx, r0, L0)
        c = (rng.standard_normal(kx.size) + 1j * rng.standard_normal(kx.size)) * np.sqrt(var)
        # The 24 frequencies take 7 values per axis: sum the coefficients on that 7 x 7 grid,
        # then Re(E_y^T C E_x) as 7 outer products (no BLAS call: tiny threaded GEMMs are slow).
        freqs, ix = np.unique(np.concatenate([kx, ky]), return_inverse=True)
        grid = np.zeros((freqs.size, freqs.size), dtype=complex)
        np.add.at(grid, (ix[kx.size :], ix[: kx.size]), c)
        x = (np.arange(n) + 0.5 - n / 2) * dx
        e = np.exp(2j * math.pi * np.multiply.outer(freqs, x))  # (7, n), same for rows and columns
        g = (grid[:, :, None] * e[None, :, :]).sum(axis=1)  # (7, n): C E_x
        low = np.zeros((n, n))
        for a in range(freqs.size):
            low += np.multiply.outer(e[a].real, g[a].real)
            low -= np.multiply.outer(e[a].imag, g[a].imag)
        screen = screen + (low - low.mean())
    return screen * _NM_PER_RAD


# ------------------------------------------------------------------------------- atmosphere


@dataclass(frozen=True)
class Layer:
    """One frozen-flow layer.  ``weight`` is its fraction of the Cn^2 integral (the
    weights of an atmosphere are normalised to sum 1); the wind blows towards
    ``wind_direction_deg`` (0 = +x, columns; 90 = +y, rows).  ``altitude_m`` is recorded for
    the profile; on axis it does not change the OPD."""

    altitude_m: float = 0.0
    weight: float = 1.0
    wind_speed_m_s: float = defaults.WIND_M_S
    wind_direction_deg: float = 0.0

    def __post_init__(self):
        if not (0.0 <= self.altitude_m <= 1e5):
            raise InputError(f"layer altitude must be in 0..100000 m, got {self.altitude_m:g}")
        if not (0.0 <= self.weight < np.inf):
            raise InputError(f"layer Cn2 weight must be a finite number >= 0, got {self.weight:g}")
        if not (0.0 <= self.wind_speed_m_s <= LAYER_WIND_MAX_M_S):
            raise InputError(f"layer wind speed must be in 0..{LAYER_WIND_MAX_M_S:g} m/s, got {self.wind_speed_m_s:.10g}")
        if not np.isfinite(self.wind_direction_deg):
            raise InputError(f"wind direction must be a finite angle in degrees, got {self.wind_direction_deg:g}")


# A proposal for Mt. Graham (docs/physics.md): Masciadri et al. 2010 (MNRAS 404, 144) find
# half of the turbulence within 80 ± 15 m of the ground; the split of the rest, the heights,
# the speed ratios and the directions are soulctl's choice.  (altitude m, Cn2 weight, speed
# relative to the ground layer, direction deg)
_LBT_PROFILE = (
    (0.0, 0.50, 1.0, 0.0),
    (500.0, 0.15, 1.4, 20.0),
    (4000.0, 0.15, 2.4, 45.0),
    (10000.0, 0.20, 5.0, 90.0),
)


def effective_wind_speed(layers) -> float:
    """Cn^2-weighted 5/3-moment of the wind speeds, v_eff = (Σ w_i v_i^(5/3))^(3/5) (weights
    normalised); tau0 = 0.314 r0 / v_eff."""
    w = np.array([layer.weight for layer in layers], dtype=float)
    v = np.array([layer.wind_speed_m_s for layer in layers], dtype=float)
    return float(np.sum(w / w.sum() * v ** (5 / 3)) ** (3 / 5))


@dataclass(frozen=True)
class AtmosphereConfig:
    seeing_arcsec: float = defaults.SEEING_ARCSEC  # at 500 nm, on the line of sight
    L0_m: float = defaults.L0_M
    layers: tuple[Layer, ...] = (Layer(),)

    def __post_init__(self):
        SEEING_ARCSEC.check(self.seeing_arcsec, "seeing")
        if not (self.L0_m > 0):  # inf allowed: Kolmogorov
            raise InputError(f"outer scale L0 must be > 0 m (inf for Kolmogorov), got {self.L0_m:g}")
        layers = tuple(self.layers)
        object.__setattr__(self, "layers", layers)
        if not layers:
            raise InputError("an atmosphere needs at least one layer, got none")
        if not all(isinstance(layer, Layer) for layer in layers):
            raise InputError("layers must be Layer objects")
        if not (sum(layer.weight for layer in layers) > 0):
            raise InputError("layer Cn2 weights must be >= 0 with a sum > 0, got all zero")

    @property
    def r0_m(self) -> float:
        """Fried parameter at 500 nm: 0.98 * 500 nm / seeing."""
        return r0_from_seeing(self.seeing_arcsec)

    @property
    def weights(self) -> tuple[float, ...]:
        total = sum(layer.weight for layer in self.layers)
        return tuple(layer.weight / total for layer in self.layers)

    @property
    def effective_wind_speed_m_s(self) -> float:
        return effective_wind_speed(self.layers)

    @classmethod
    def lbt_default(
        cls, seeing_arcsec: float = defaults.SEEING_ARCSEC, L0_m: float = defaults.L0_M, wind_speed_m_s: float = defaults.WIND_M_S
    ) -> AtmosphereConfig:
        """Four layers for Mt. Graham (a proposal; half the Cn^2 at the ground as Masciadri et
        al. 2010 measured below 80 m), speeds scaled so that v_eff = wind_speed_m_s."""
        WIND_M_S.check(wind_speed_m_s, "the effective wind speed")
        w = np.array([p[1] for p in _LBT_PROFILE])
        rel = np.array([p[2] for p in _LBT_PROFILE])
        scale = wind_speed_m_s / float(np.sum(w * rel ** (5 / 3)) ** (3 / 5))
        layers = tuple(Layer(h, wi, scale * s, d) for (h, wi, s, d) in _LBT_PROFILE)
        return cls(seeing_arcsec, L0_m, layers)


def _default_screen_pixels(n_pixels: int, pixel_scale_m: float, L0_m: float) -> int:
    need = max(4.0 * L0_m / pixel_scale_m, 8.0 * n_pixels)
    if not np.isfinite(need) or need >= _SCREEN_CAP:
        return max(_SCREEN_CAP, 1 << int(math.ceil(math.log2(n_pixels))))
    return 1 << int(math.ceil(math.log2(need)))


class FrozenFlowAtmosphere:
    """Frozen-flow layers moving across the pupil: OPD (nm) on an n_pixels grid at any time.

    One periodic FFT screen per layer (no subharmonics: it wraps seamlessly), r0_i =
    r0 w_i^(-3/5), independent generators spawned from ``seed``.  Screen size: at least the
    smallest power of two >= max(4 L0, 8 pupils) in pixels, at most 4096, along both axes
    (``screen_pixels``); spatial frequencies below 1/screen size are missing: < 0.1% of the
    tilt variance for L0 <= 100 m at the default size, but 17-25% for L0 = 10 km and 28-35%
    for Kolmogorov (80-160 px across 8.2 m; docs/physics.md).  **No repetition within
    ``duration_s``**: a layer's screen is the rectangle (even FFT sizes, no side below the
    default) of least area on which the pupil, moving v duration_s, never reaches screen it
    has shown (``_screen_shapes``): long along the wind's axis, or for a wind at an angle a
    skewed torus, on which the path wraps many times and runs beside its earlier passes at
    least a quarter of the default size apart; up to ``MAX_SCREEN_PIXELS`` for all layers.
    ``repeat_time_s`` is the first time a layer does show screen again (for longer runs the
    screens wrap, as they all did before).
    The OPD at pupil pixel x is the screen at x - v t (the pattern moves with the wind): the
    screen's Fourier series, evaluated once on a grid twice as fine (``band_limited_upsample``),
    interpolated there with periodic cubic B-splines (``fine_spline_coefficients``, in the
    same Fourier pass).  At whole-pixel offsets this is the screen itself; at fractional ones a
    band-limited translation to within 0.2 % of the 500-mode fitting error (bilinear
    interpolation on the screen's own grid low-passed it by cos(pi f), 14 % at half a pixel,
    so the statistics varied with the wind's sub-pixel phase; quintic splines there 1.5-2 %:
    docs/physics.md).  Memory: 24 bytes per screen pixel and layer (the screen, float64, and
    the coefficients on the finer grid, float32: 25 MB at 1024^2, 400 MB at 4096^2, 4.8 GB at
    ``MAX_SCREEN_PIXELS``; set-up holds about twice the largest layer's more); set-up ~0.2 s
    per layer at 1024^2.
    """

    def __init__(
        self,
        config: AtmosphereConfig,
        n_pixels: int,
        pixel_scale_m: float,
        seed: int,
        screen_pixels: int | None = None,
        duration_s: float | None = None,
    ):
        if not isinstance(config, AtmosphereConfig):
            raise InputError("config must be an AtmosphereConfig")
        if int(n_pixels) != n_pixels or n_pixels < 2:
            raise InputError(f"pupil sampling must be an integer >= 2 pixels, got {n_pixels}")
        self.config = config
        self.n_pixels = int(n_pixels)
        self.pixel_scale_m = _check_positive("pixel scale", pixel_scale_m, "m")
        if screen_pixels is None:
            screen_pixels = _default_screen_pixels(self.n_pixels, self.pixel_scale_m, config.L0_m)
        if int(screen_pixels) != screen_pixels or not (self.n_pixels <= screen_pixels <= 16384):
            raise InputError(f"screen size must be an integer in {self.n_pixels}..16384 pixels (>= the pupil), got {screen_pixels}")
        self.screen_pixels = int(screen_pixels)
        if duration_s is not None and not (math.isfinite(duration_s) and duration_s >= 0):
            raise InputError(f"the frozen flow's duration must be a finite number of seconds >= 0, got {duration_s}")

        weights = config.weights
        rngs = np.random.default_rng(seed).spawn(len(config.layers))
        self._window = UPSAMPLING * (self.n_pixels - 1) + SPLINE_ORDER + 1  # fine samples a pupil row reads
        self.layer_r0_m = tuple(config.r0_m * w ** (-3 / 5) if w > 0 else np.inf for w in weights)
        active = [i for i, w in enumerate(weights) if w > 0]
        vel = [_velocity_px_s(config.layers[i], self.pixel_scale_m) for i in active]
        shapes = _screen_shapes(vel, duration_s or 0.0, self.n_pixels, self.screen_pixels)
        built: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        for j in sorted(range(len(active)), key=lambda j: -math.prod(shapes[j])):  # largest first: the lowest peak memory
            i = active[j]
            built[j] = self._layer(shapes[j], self.layer_r0_m[i], config.L0_m, rngs[i])
        screens = [built[j][0] for j in range(len(active))]
        coefficients = [built[j][1] for j in range(len(active))]
        self._screens = tuple(screens)
        self._coefficients = tuple(coefficients)
        self._velocity_px_s = tuple(vel)
        self.screen_shapes: tuple[tuple[int, int], ...] = tuple(shapes)
        self._repeat_time_s = self._first_repeat()

    def _layer(self, shape: tuple[int, int], r0_m: float, L0_m: float, rng) -> tuple[np.ndarray, np.ndarray]:
        """A layer's periodic screen (nm, read-only) and its padded spline coefficients (every
        window a contiguous slice)."""
        screen = _NM_PER_RAD * periodic_phase_screen(shape, self.pixel_scale_m, r0_m, L0_m, rng)
        screen.setflags(write=False)
        return screen, fine_spline_coefficients(screen, pad=self._window)

    @property
    def layer_screens_nm(self) -> tuple[np.ndarray, ...]:
        """The (read-only) periodic screens of the layers with a non-zero weight, OPD in nm."""
        return self._screens

    @property
    def repeat_time_s(self) -> float:
        """The first time a layer's pupil footprint reaches screen it has shown before (inf if
        none moves, or none within ``REPEAT_HORIZON_S``): ``_first_repeat_s`` of the layers,
        (screen - pupil) / |v| for a wind along an axis."""
        return self._repeat_time_s

    def _first_repeat(self) -> float:
        times = (
            _first_repeat_s(velocity, shape, self.n_pixels, REPEAT_HORIZON_S)
            for shape, velocity in zip(self.screen_shapes, self._velocity_px_s)
        )
        return min(times, default=math.inf)

    def opd_nm(self, t_s: float) -> np.ndarray:
        """OPD (nm, float64, n_pixels x n_pixels) at time t_s: the sum of the layers, each
        translated by v_i t along its direction (see the class).  The same numbers as
        ``scipy.ndimage.map_coordinates(fine screen, 2 (pupil grid - v t), order=3,
        mode='grid-wrap')``, computed from the stored coefficients as one gathered window and
        4 + 4 weighted, strided row and column sums (a pure translation is separable)."""
        t = float(t_s)
        if not np.isfinite(t):
            raise InputError(f"time must be a finite number of seconds, got {t_s}")
        stride, n = UPSAMPLING, self.n_pixels
        out = np.zeros((n, n))
        for coefficients, (vx, vy), (ny, nx) in zip(self._coefficients, self._velocity_px_s, self.screen_shapes):
            Ny, Nx = stride * ny, stride * nx  # the finer grid's size
            # pupil pixel (r, c) sees screen point (r - vy t, c - vx t), fine point stride x that, modulo N
            py = -math.fmod(stride * vy * t, Ny)
            px = -math.fmod(stride * vx * t, Nx)
            iy, ix = math.floor(py), math.floor(px)
            r0, c0 = (iy - SPLINE_ORDER // 2) % Ny, (ix - SPLINE_ORDER // 2) % Nx
            window = coefficients[r0 : r0 + self._window, c0 : c0 + self._window]
            out += separable_sums(window, bspline_weights(py - iy), bspline_weights(px - ix), stride, n)
        return out


MAX_SCREEN_PIXELS = 200 << 20  # all layers together (4.8 GB with their coefficients): longer runs wrap
SPLINE_MARGIN_PX = 2  # coarse pixels the spline taps read beyond the pupil
REPEAT_HORIZON_S = 86400.0  # ``repeat_time_s`` looks this far ahead (inf beyond)
_MAX_WRAPS = 10**6  # and at most this many wraps of the screen


def _velocity_px_s(layer: Layer, pixel_scale_m: float) -> tuple[float, float]:
    """(vx, vy) of a layer in pixels per second (exact zeros along the axes)."""
    a = math.radians(layer.wind_direction_deg)
    v = layer.wind_speed_m_s / pixel_scale_m
    c, s = (0.0 if abs(u) < 1e-12 else u for u in (math.cos(a), math.sin(a)))  # 90°: exact
    return v * c, v * s


def _even_fft_size(n: int) -> int:
    m = scipy.fft.next_fast_len(n)
    while m % 2:
        m = scipy.fft.next_fast_len(m + 1)
    return m


def _first_repeat_s(velocity: tuple[float, float], shape: tuple[int, int], width: int, horizon_s: float) -> float:
    """The first time in (0, horizon_s] at which a square footprint of ``width`` px, moving at
    (vx, vy) px/s on the periodic ny x nx screen, overlaps screen it has already covered (inf
    if none): a repeat is a lattice point (a nx, b ny) != 0 within ``width`` of the path v dt
    along both axes.  A path at an angle to the axes wraps many times before it comes back
    beside itself (a "skewed torus"); along an axis it returns after (n - width) / |v|."""
    (ny, nx), (vx, vy) = shape, (abs(velocity[0]), abs(velocity[1]))
    if vy > vx:  # enumerate the wraps of the faster axis: at most 3 of the other per wrap
        (ny, nx), (vx, vy) = (nx, ny), (vy, vx)
    if vx == 0:
        return math.inf
    if min(nx, ny) < width:
        return 0.0  # the footprint is wider than the screen: it overlaps its own wrap
    a = np.arange(0, min(math.floor((vx * horizon_s + width) / nx), _MAX_WRAPS) + 1, dtype=float)
    lo_x, hi_x = np.maximum((a * nx - width) / vx, 0.0), (a * nx + width) / vx  # |vx dt - a nx| < width
    best = math.inf
    b0 = np.floor(vy * lo_x / ny)
    for db in (-1.0, 0.0, 1.0, 2.0, 3.0):  # every b with |b ny - vy dt| < width in the window (ny >= width)
        b = b0 + db
        if vy > 0:
            lo, hi = np.maximum(lo_x, (b * ny - width) / vy), np.minimum(hi_x, (b * ny + width) / vy)
        else:
            lo, hi = lo_x, np.where(np.abs(b * ny) < width, hi_x, -np.inf)
        ok = (lo < hi) & (b >= 0) & ((a > 0) | (b > 0)) & (lo <= horizon_s)
        if ok.any():
            best = min(best, float(lo[ok].min()))
    return best


def _even_fast_sizes(lo: int, hi: int) -> list[int]:
    """The even FFT sizes (2^a 3^b 5^c, a >= 1) in [lo, hi], ascending."""
    sizes = set()
    p2 = 2
    while p2 <= hi:
        p3 = p2
        while p3 <= hi:
            p5 = p3
            while p5 <= hi:
                if p5 >= lo:
                    sizes.add(p5)
                p5 *= 5
            p3 *= 3
        p2 *= 2
    return sorted(sizes)


def _box_shape(velocity: tuple[float, float], seconds: float, n_pixels: int, minimum: int) -> tuple[int, int]:
    """(ny, nx) long enough along each axis for the pupil to cross |v_axis| seconds of screen."""

    def axis(v: float) -> int:
        span = math.ceil(abs(v) * seconds) + n_pixels + SPLINE_MARGIN_PX
        return minimum if span <= minimum else _even_fft_size(span)

    return axis(velocity[1]), axis(velocity[0])


def _smallest_shape(
    velocity: tuple[float, float], seconds: float, n_pixels: int, minimum: int, max_area: float = math.inf
) -> tuple[int, int]:
    """The screen of least area, both sides >= ``minimum``, on which the pupil (with the
    spline's margin) sees no screen twice within ``seconds``: the box (``_box_shape``: no wrap
    at all) when it is ``minimum`` square, else the best of the box and the skewed tori no
    larger than it (or than ``max_area``: none above it is looked at).  On a skewed torus the
    path runs beside its earlier passes: they are kept ``minimum`` / 4 apart (L0 at the
    default size, 25 m: two pupils 25 m apart have a Tip/Tilt correlation of ~0.01, 0.2-0.3
    at 8.4 m), not just a pupil."""
    width = max(n_pixels + SPLINE_MARGIN_PX, minimum // 4)
    box = _box_shape(velocity, seconds, n_pixels, minimum)
    if box == (minimum, minimum) or velocity[0] == 0 or velocity[1] == 0:
        return box
    best, area = box, min(box[0] * box[1], max_area)
    ys, xs = _even_fast_sizes(minimum, box[0]), _even_fast_sizes(minimum, box[1])
    # passes >= width apart in both axes are >= width / sqrt(2) apart across the path: a torus
    # holds |v| seconds of path only if its area is at least that times width / sqrt(2)
    least = width / math.sqrt(2) * math.hypot(*velocity) * seconds
    for nx in xs:
        if nx * minimum >= area:
            break
        for ny in ys[bisect.bisect_left(ys, least / nx) :]:
            if nx * ny >= area:
                break
            if _first_repeat_s(velocity, (ny, nx), width, seconds) > seconds:
                best, area = (ny, nx), nx * ny
                break
    return best


def _screen_shapes(velocities: list[tuple[float, float]], duration_s: float, n_pixels: int, minimum: int) -> list[tuple[int, int]]:
    """(ny, nx) of each layer's screen: ``minimum`` square, or the smallest rectangle on which
    the pupil does not come back to screen it has shown within ``duration_s``
    (``_smallest_shape``: long along the wind's axis, or a skewed torus for a wind at an
    angle).  Where the layers together would pass MAX_SCREEN_PIXELS (never below their
    ``minimum`` squares), the longest time the budget allows for all of them (bisection): the
    atmosphere repeats no earlier than it must."""
    budget = max(MAX_SCREEN_PIXELS, len(velocities) * minimum**2)

    def shapes(seconds: float, limit: float = math.inf) -> list[tuple[int, int]]:
        return [_smallest_shape(v, seconds, n_pixels, minimum, limit) for v in velocities]

    def fits(seconds: float) -> bool:
        return sum(math.prod(shape) for shape in shapes(seconds, budget)) <= budget

    if fits(duration_s):
        return shapes(duration_s)
    lo, hi = 0.0, duration_s
    while hi - lo > 1e-3 * hi:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if fits(mid) else (lo, mid)
    return shapes(lo)
