"""Tip/Tilt IIR filter design (paper, Sec. 2.3; the semi-analytical routine of Agapito et al.
2012): minimise the residual Tip/Tilt variance of one axis

    J = int |S|^2 Phi_dist df + int |T|^2 Phi_noise df            (temporal error + noise)
        + |T(127 Hz)|^2 sigma_127^2                                (the ASM resonance term)

over the N_f = 8 filter H(z) = g prod_4 (1 - beta z^-1) / [(1 - z^-1) prod_3 (1 - alpha z^-1)]
(4 zeros, 4 poles, one pole fixed at z = 1 for integral action), subject to the modulus
margin |1 + H P| > epsilon on the whole band up to Nyquist and a stable closed loop.

* Phi_dist: turbulent Tip/Tilt (``disturbance.turbulence``) + the vibration lines
  (``disturbance.vibrations``), the mean of the two axes.
* Phi_noise: white measurement noise of ``noise_mas`` RMS per frame.
* The 127 Hz line (2 mas by default) is not a disturbance to reject: as the paper says, it is
  there only to keep the loop's response at the ASM's control-structure resonance low.  The
  resonance is excited by the commands, whose response to any input is T, so the line is
  weighted by |T|^2.

Roots are real, in -0.99..0.99, as in the paper's table; the gain is optimised with them.
The search is scipy's differential evolution (vectorised over the population, seeded, hence
reproducible), then a Nelder-Mead polish.  The best integrator is found under the same
constraint and cost, for comparison.
"""

from __future__ import annotations

import csv
import io
import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import brentq, differential_evolution, minimize

from .. import blas, tables
from ..disturbance.turbulence import TurbulenceTipTilt
from ..disturbance.vibrations import VibrationSpectrum
from ..errors import InputError
from ..tables import GAIN_COLUMN, ROOT_COLUMNS
from .delay import DelayModel
from .filters import Filter
from .transfer import RESONANCE_HZ, Loop, LoopAnalysis, Plant, analyze, frequency_grid, max_stable_gain

ROOT_BOUND = 0.99
GAIN_BOUNDS = (0.01, 4.0)
N_ZEROS, N_FREE_POLES = 4, 3


@dataclass(frozen=True)
class Disturbance:
    """What the filter must reject (Tip/Tilt, mas) and the noise it must not propagate."""

    turbulence: TurbulenceTipTilt = field(default_factory=TurbulenceTipTilt)
    vibrations: VibrationSpectrum = field(default_factory=VibrationSpectrum.lbt_default)
    noise_mas: float = 1.0  # white measurement noise, RMS per frame and axis (an R ~ 10 star, docs/physics.md)
    resonance_hz: float = RESONANCE_HZ
    resonance_mas: float = 2.0  # the paper's 2 mas RMS line at 127 Hz

    def __post_init__(self):
        if not (0 <= self.noise_mas < 1e4):
            raise InputError(f"noise must be in 0..1e4 mas RMS per frame, got {self.noise_mas:g}")
        if not (0 <= self.resonance_mas < 1e4):
            raise InputError(f"the 127 Hz line must be in 0..1e4 mas RMS, got {self.resonance_mas:g}")

    def psd(self, f_hz) -> np.ndarray:
        """Disturbance PSD (mas^2/Hz, mean of Tip and Tilt)."""
        return self.turbulence.psd(f_hz) + self.vibrations.psd(f_hz)


def _cost_grid(rate_hz: float, disturbance: Disturbance, n: int = 1200) -> np.ndarray:
    """Log-spaced frequencies up to Nyquist, refined across each vibration line."""
    nyquist = rate_hz / 2.0
    f = np.geomspace(1e-2, nyquist, n)
    for line in disturbance.vibrations.lines:
        if line.frequency_hz < nyquist:
            half = max(25.0 * line.damping * line.frequency_hz, 0.5)
            f = np.union1d(f, np.linspace(max(line.frequency_hz - half, 1e-2), min(line.frequency_hz + half, nyquist), 201))
    return f


def _trapezoid_weights(f: np.ndarray) -> np.ndarray:
    w = np.zeros_like(f)
    d = np.diff(f)
    w[:-1] += d / 2
    w[1:] += d / 2
    return w


def _poly_from_roots(roots: np.ndarray) -> np.ndarray:
    """Rows of prod(1 - r z^-1) coefficients for a batch of root sets, roots (S, k)."""
    c = np.ones((roots.shape[0], 1))
    for r in roots.T:
        nxt = np.zeros((c.shape[0], c.shape[1] + 1))
        nxt[:, :-1] += c
        nxt[:, 1:] -= r[:, None] * c
        c = nxt
    return c


class DesignCost:
    """The cost and constraints on fixed frequency grids, vectorised over parameter sets
    theta = [beta_1..4, alpha_1..3, g] (columns)."""

    def __init__(self, rate_hz: float, plant: Plant, disturbance: Disturbance, epsilon: float):
        if not (0 < epsilon < 1):
            raise InputError(f"epsilon must be in (0, 1) exclusive, got {epsilon:g}")
        self.rate_hz, self.plant, self.disturbance, self.epsilon = rate_hz, plant, disturbance, epsilon
        nyquist = rate_hz / 2.0
        f = _cost_grid(rate_hz, disturbance)
        self.f = f
        self.weights = _trapezoid_weights(f)
        self.phi_dist = disturbance.psd(f)
        self.phi_noise = np.full(f.shape, disturbance.noise_mas**2 / nyquist)  # one-sided white
        self.line_var = disturbance.resonance_mas**2 if disturbance.resonance_hz < nyquist else 0.0
        self.f_check = frequency_grid(rate_hz, 1500)
        self._cost_basis = self._basis(f)
        self._check_basis = self._basis(self.f_check)
        self._line_basis = self._basis(np.array([min(disturbance.resonance_hz, nyquist)]))
        if plant.structure is not None:  # the batched stability check uses P's numerator only
            raise InputError("the Tip/Tilt design takes a plant without a structural resonance")
        self._plant_num = plant.numerator()

    def _basis(self, f: np.ndarray):
        w = 2 * np.pi * f / self.rate_hz
        powers = np.exp(-1j * np.outer(np.arange(N_ZEROS + N_FREE_POLES + 2), w))
        return powers, self.plant.frequency_response(w)

    @staticmethod
    def split(theta: np.ndarray):
        theta = np.asarray(theta, dtype=float)
        theta = theta.reshape(theta.shape[0], -1)
        return theta[:N_ZEROS].T, theta[N_ZEROS : N_ZEROS + N_FREE_POLES].T, theta[-1]

    def _open_loop(self, num, den, gain, basis):
        powers, plant = basis
        return gain[:, None] * (num @ powers[: num.shape[1]]) / (den @ powers[: den.shape[1]]) * plant[None, :]

    def evaluate(self, theta: np.ndarray) -> dict[str, np.ndarray]:
        """Per parameter set: the cost terms (mas^2), the modulus margin and stability."""
        zeros, poles, gain = self.split(theta)
        num = _poly_from_roots(zeros)
        den = _poly_from_roots(np.column_stack([poles, np.ones(poles.shape[0])]))
        L = self._open_loop(num, den, gain, self._cost_basis)
        s2 = 1.0 / np.abs(1.0 + L) ** 2
        t2 = np.abs(L) ** 2 * s2
        temporal = (s2 * self.phi_dist) @ self.weights
        noise = (t2 * self.phi_noise) @ self.weights
        Lr = self._open_loop(num, den, gain, self._line_basis)[:, 0]
        line = self.line_var * np.abs(Lr / (1.0 + Lr)) ** 2
        margin = np.min(np.abs(1.0 + self._open_loop(num, den, gain, self._check_basis)), axis=1)
        return {"temporal": temporal, "noise": noise, "line": line, "modulus_margin": margin, "stable": self._stable(num, den, gain)}

    def _stable(self, num, den, gain) -> np.ndarray:
        """Closed-loop poles (roots of den + g num p) inside the unit circle, by batched
        companion-matrix eigenvalues."""
        bp = gain[:, None] * np.apply_along_axis(np.convolve, 1, num, self._plant_num)
        size = max(den.shape[1], bp.shape[1])
        c = np.pad(den, ((0, 0), (0, size - den.shape[1]))) + np.pad(bp, ((0, 0), (0, size - bp.shape[1])))
        n = size - 1
        comp = np.zeros((c.shape[0], n, n))
        comp[:, 0, :] = -c[:, 1:] / c[:, :1]
        comp[:, np.arange(1, n), np.arange(n - 1)] = 1.0
        return np.max(np.abs(np.linalg.eigvals(comp)), axis=1) < 1.0 - 1e-9

    def penalised(self, theta: np.ndarray) -> np.ndarray:
        """J, with infeasible sets ranked after every feasible one."""
        e = self.evaluate(theta)
        j = e["temporal"] + e["noise"] + e["line"]
        bad_margin = e["modulus_margin"] < self.epsilon
        j = np.where(bad_margin, 1e9 * (1.0 + self.epsilon - e["modulus_margin"]), j)
        return np.where(e["stable"], j, 1e10)


def filter_theta(f: Filter) -> np.ndarray:
    """theta of a filter of the designed family (an integrator: zeros and free poles at 0)."""
    poles = list(f.poles)
    poles.remove(1.0)
    zeros = list(f.zeros) + [0.0] * (N_ZEROS - len(f.zeros))
    poles = poles + [0.0] * (N_FREE_POLES - len(poles))
    if len(zeros) != N_ZEROS or len(poles) != N_FREE_POLES:
        raise InputError("the design family is 4 zeros and 4 poles with one at z = 1")
    return np.array([*zeros, *poles, f.gain], dtype=float)


def theta_filter(theta) -> Filter:
    zeros, poles, gain = DesignCost.split(theta)
    return Filter.iir(tuple(sorted(float(z) for z in zeros[0])), tuple(sorted(float(p) for p in poles[0])) + (1.0,), float(gain[0]))


@dataclass(frozen=True)
class Controller:
    """One designed controller with its figures."""

    filter: Filter
    analysis: LoopAnalysis
    jitter_mas: float  # residual per axis: sqrt(temporal + noise), the 127 Hz term left out
    cost_mas2: float  # the minimised J, the 127 Hz term included

    def to_dict(self) -> dict:
        return {
            "zeros": [float(z.real) for z in self.filter.zeros],
            "poles": [float(p.real) for p in self.filter.poles],
            "gain": self.filter.gain,
            "jitter_mas": self.jitter_mas,
            "cost_mas2": self.cost_mas2,
            **self.analysis.to_dict(),
        }


@dataclass(frozen=True)
class DesignResult:
    rate_hz: float
    delay_frames: float
    epsilon: float
    iir: Controller
    integrator: Controller
    table: Controller | None  # the built-in roots table's filter at this rate, at its best gain
    runtime_s: float
    evaluations: int
    in_use: Controller | None = None  # the filter a recorded loop ran (an identified plant's), at its own gain

    @property
    def rejection_ratio(self) -> float:
        """|S_int(13 Hz)| / |S_iir(13 Hz)|: how much better the IIR rejects the 13 Hz line."""
        integrator, iir = self.integrator.analysis.rejection_13hz, self.iir.analysis.rejection_13hz
        assert integrator is not None and iir is not None  # the designs run at rates that sample 13 Hz
        return integrator / iir

    def to_dict(self) -> dict:
        return {
            "rate_hz": self.rate_hz,
            "delay_frames": self.delay_frames,
            "epsilon": self.epsilon,
            "iir": self.iir.to_dict(),
            "integrator": self.integrator.to_dict(),
            "table": self.table.to_dict() if self.table else None,
            "in_use": self.in_use.to_dict() if self.in_use else None,
            "rejection_ratio_13hz": self.rejection_ratio,
            "runtime_s": self.runtime_s,
            "evaluations": self.evaluations,
        }


def _controller(cost: DesignCost, f: Filter) -> Controller:
    e = cost.evaluate(filter_theta(f))
    analysis = analyze(Loop(f, cost.plant, cost.rate_hz), resonance_hz=cost.disturbance.resonance_hz)
    return Controller(
        f, analysis, float(math.sqrt(e["temporal"][0] + e["noise"][0])), float(e["temporal"][0] + e["noise"][0] + e["line"][0])
    )


def best_gain(cost: DesignCost, shape: Filter) -> Filter:
    """The gain minimising the cost for a filter of fixed zeros and poles, under the same
    modulus margin: the best integrator, or the best gain for a tabulated filter."""

    def theta(g):
        return filter_theta(shape.with_gain(g))

    def margin(g):
        return cost.evaluate(theta(g))["modulus_margin"][0] - cost.epsilon

    # The largest gain that keeps the margin: below the stability limit, where it is 0.
    g_max = min(max_stable_gain(Loop(shape.with_gain(1.0), cost.plant, cost.rate_hz)), GAIN_BOUNDS[1])
    if not g_max > 0:
        raise InputError(f"the filter {shape.zeros} / {shape.poles} is unstable at any gain")
    hi = brentq(margin, 1e-6, g_max, xtol=1e-9) if margin(g_max) < 0 else g_max
    gains = np.linspace(hi / 400, hi, 400)
    j = cost.penalised(np.stack([theta(g) for g in gains], axis=1))
    i = int(np.argmin(j))
    lo_g, hi_g = gains[max(i - 1, 0)], gains[min(i + 1, gains.size - 1)]
    res = minimize(
        lambda x: cost.penalised(theta(float(x[0])))[0],
        [gains[i]],
        method="Nelder-Mead",
        bounds=[(lo_g, hi_g)],
        options={"xatol": 1e-6, "fatol": 1e-10},
    )
    return shape.with_gain(float(res.x[0]) if res.fun <= j[i] else float(gains[i]))


@blas.on_one_thread  # 5-term products over (135, 5000) grids: a second BLAS thread doubled the CPU time, saved no wall time
def design_tt_filter(
    rate_hz: float,
    disturbance: Disturbance | None = None,
    epsilon: float = 0.2,
    delay_frames: float | None = None,
    seed: int = 1,
    maxiter: int = 400,
    popsize: int = 15,
    in_use: Filter | None = None,
) -> DesignResult:
    """Design the N_f = 8 Tip/Tilt IIR filter at one frame rate (see the module docstring).
    The delay defaults to SOUL's delay model at that rate; ``in_use``, a filter to evaluate
    beside the design at its own gain (the one a recorded loop ran)."""
    if not (rate_hz > 0 and math.isfinite(rate_hz)):
        raise InputError(f"frame rate must be a finite number > 0 Hz, got {rate_hz:g}")
    start = time.perf_counter()
    disturbance = disturbance or Disturbance()
    d = DelayModel.from_table().frames(rate_hz) if delay_frames is None else delay_frames
    plant = Plant(d)
    cost = DesignCost(rate_hz, plant, disturbance, epsilon)
    bounds = [(-ROOT_BOUND, ROOT_BOUND)] * (N_ZEROS + N_FREE_POLES) + [GAIN_BOUNDS]
    integ = best_gain(cost, Filter.integrator(1.0))
    init = _initial_population(integ, popsize * len(bounds), seed)
    best, evaluations = _search(cost, bounds, init, seed, maxiter, popsize)
    tabulated = [r for r in tables.tt_iir_table() if r.frame_rate_hz == rate_hz]
    table_shape = Filter.iir(tabulated[0].zeros, tabulated[0].poles, 1.0) if tabulated else None
    if cost.penalised(best)[0] >= 1e9:
        raise InputError(
            f"no stable filter meets the modulus margin epsilon = {epsilon:g} at {rate_hz:g} Hz "
            f"with a {d:.2f}-frame delay: try a smaller epsilon"
        )
    return DesignResult(
        rate_hz=float(rate_hz),
        delay_frames=float(d),
        epsilon=float(epsilon),
        iir=_controller(cost, theta_filter(best)),
        integrator=_controller(cost, integ),
        table=_controller(cost, best_gain(cost, table_shape)) if table_shape else None,
        runtime_s=time.perf_counter() - start,
        evaluations=evaluations,
        in_use=_controller(cost, in_use) if in_use is not None else None,
    )


def _search(cost: DesignCost, bounds: list, init: np.ndarray, seed: int, maxiter: int, popsize: int) -> tuple[np.ndarray, int]:
    """(best theta, cost evaluations): differential evolution, then a Nelder-Mead polish."""
    res = differential_evolution(
        cost.penalised,
        bounds,
        vectorized=True,
        updating="deferred",
        seed=np.random.default_rng(seed),  # a Generator: every seed the CLI accepts (0..2^63-1), not only the legacy 32-bit ones
        maxiter=maxiter,
        popsize=popsize,
        tol=1e-7,
        init=init,
        polish=False,
    )
    polished = minimize(
        lambda x: float(cost.penalised(x)[0]),
        res.x,
        method="Nelder-Mead",
        bounds=bounds,
        options={"xatol": 1e-7, "fatol": 1e-9, "maxiter": 4000},
    )
    best = polished.x if polished.fun <= res.fun else res.x
    return best, int(res.nfev * popsize * len(bounds) + polished.nfev)


def _initial_population(integ: Filter, n: int, seed: int) -> np.ndarray:
    """Uniform random starts, plus the best integrator so that the search starts from a
    feasible point (the roots table is not used: the design must find its filters alone)."""
    rng = np.random.default_rng(seed)
    pop = rng.uniform(-ROOT_BOUND, ROOT_BOUND, size=(n, N_ZEROS + N_FREE_POLES + 1))
    pop[:, -1] = rng.uniform(GAIN_BOUNDS[0], 2.0, size=n)
    pop[0] = filter_theta(integ)
    return pop


def roots_table_csv(results: list[DesignResult], header: str) -> str:
    """A roots table in the format of tables/tt_iir_roots.csv and the designed gain of each row
    (its ``gain`` column: ``configure --roots`` starts the loop at it)."""
    out = io.StringIO()
    for line in header.splitlines():
        out.write(f"# {line}\n")
    w = csv.writer(out, lineterminator="\n")
    w.writerow([*ROOT_COLUMNS, GAIN_COLUMN])
    for r in sorted(results, key=lambda r: -r.rate_hz):
        f = r.iir.filter
        w.writerow([f"{r.rate_hz:g}", *[f"{z.real:.4f}" for z in f.zeros], *[f"{p.real:.4f}" for p in f.poles], f"{f.gain:.4f}"])
    return out.getvalue()
