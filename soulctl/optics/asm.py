"""The adaptive secondary (LBT672): actuator geometry, influence functions and the modal basis.

* Actuators: 672 on 14 concentric rings, evenly spaced in radius between the central
  obstruction and the pupil edge, each ring holding a number of actuators proportional to its
  circumference (largest-remainder rounding to 672).  The projected pitch is then ~0.27 m
  radially and ~0.31 m along the rings, the LBT672's ~0.3 m (Riccardi et al. 2003).  The exact
  layout of the shell is not public in machine-readable form: this is a proposal with the
  right count, rings and pitch.
* Influence functions (``AsmGeometry.influence``), two models:
  - ``"gaussian"``: ``exp(ln(c) (r/p)^2)`` with ``p`` the mean pitch and the coupling
    ``c = 0.15`` at one pitch (a proposal in the range of thin-shell ASMs, where the force
    actuators and the shell's stiffness give broad, smooth responses);
  - ``"thin-plate"`` (the default): the shell as a thin plate whose every actuator holds its position (the
    LBT672's local position loops): an influence function is the surface of least bending
    energy that is 1 at its own actuator and 0 at all others, the thin-plate spline's
    cardinal function (kernel r^2 ln r, the biharmonic Green's function of an unbounded
    plate; the edge and the central hole are not modelled).  SPECULA builds its zonal
    influence functions the same way.  It fills the space between actuators as no Gaussian
    does: 500 modes fit 102.0 nm against a pupil KL's 100.7 (1.3 %; the Gaussian 108.9,
    8 %: docs/physics.md, "Adaptive secondary").
* Commands and modal coefficients are wavefront OPD in nm (the factor 2 of a reflection is in
  the calibration, not here); a unit modal coefficient is 1 nm RMS on the pupil.
* Modal basis (``kl_basis``): modes 1-2 are the mirror's least-squares Tip and Tilt; the others
  are Karhunen-Loeve modes of von Karman turbulence restricted to the mirror's space, all
  orthonormal on the pupil, piston-free, and ordered by decreasing turbulent variance (so by
  increasing spatial frequency): the double diagonalisation of Gendron (1995) done in the
  whitened actuator space.  An eigenvector's sign is arbitrary and LAPACK's choice depends
  on the BLAS threads (a basis computed with one thread flipped 149 of 671 modes against
  two), which changed what a seed gives (OGTL's probe and the push-pull calibration's noise
  act in modal coordinates): each KL mode's sign is fixed by a seeded generic actuator
  vector (``canonical_signs``).  ``M`` maps modal coefficients to actuator commands and
  ``M_inv`` (``M^T G``, G the pupil Gram matrix of the influence functions) back.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft
from scipy.sparse import csr_matrix
from scipy.spatial import cKDTree

from .. import blas, defaults
from ..errors import InputError
from .atmosphere import phase_covariance
from .pupil import LBT_DIAMETER_M, LBT_OBSTRUCTION, Pupil
from .registration import Misregistration

N_ACTUATORS = 672  # the LBT672 adaptive secondary
INFLUENCES = ("gaussian", "thin-plate")  # influence-function models (the module docstring)
DEFAULT_INFLUENCE = "thin-plate"
SIGN_SEED = 20261128  # the generic actuator vector that fixes each KL mode's sign (in the basis cache key)


@dataclass(frozen=True)
class AsmGeometry:
    n_actuators: int = N_ACTUATORS
    n_rings: int = 14
    coupling: float = 0.15
    diameter_m: float = LBT_DIAMETER_M
    obstruction: float = LBT_OBSTRUCTION
    influence: str = DEFAULT_INFLUENCE

    def __post_init__(self):
        if not (3 <= self.n_rings <= self.n_actuators):
            raise InputError(f"ASM rings must be 3..{self.n_actuators}, got {self.n_rings}")
        if not (0 < self.coupling < 1):
            raise InputError(f"influence-function coupling must be in (0, 1), got {self.coupling}")
        check_influence(self.influence)

    def ring_radii(self) -> np.ndarray:
        """Ring radii (m): the annulus [obstruction R, R] cut into n_rings - 0.5 steps, first
        ring half a step outside the obstruction, last ring on the pupil edge."""
        R = self.diameter_m / 2
        step = R * (1 - self.obstruction) / (self.n_rings - 0.5)
        return self.obstruction * R + step * (0.5 + np.arange(self.n_rings))

    def ring_counts(self) -> np.ndarray:
        r = self.ring_radii()
        exact = self.n_actuators * r / r.sum()
        counts = np.floor(exact).astype(int)
        short = self.n_actuators - counts.sum()
        counts[np.argsort(exact - counts)[::-1][:short]] += 1
        return counts

    def positions(self) -> np.ndarray:
        """(n_actuators, 2) x, y in metres, ring by ring, alternate rings rotated half a step."""
        xy = []
        for k, (r, n) in enumerate(zip(self.ring_radii(), self.ring_counts())):
            a = 2 * np.pi * (np.arange(n) + 0.5 * (k % 2)) / n
            xy.append(np.stack([r * np.cos(a), r * np.sin(a)], axis=1))
        return np.concatenate(xy)

    @property
    def pitch_m(self) -> float:
        """Mean actuator pitch: the side of the square cell each actuator covers on the annulus."""
        R = self.diameter_m / 2
        area = np.pi * R**2 * (1 - self.obstruction**2)
        return float(np.sqrt(area / self.n_actuators))

    def sparse_influence_functions(self, pupil: Pupil, floor: float = 1e-4, registration: Misregistration | None = None):
        """The same as a CSR matrix, responses below ``floor`` (of the peak, 1) dropped: for
        the Gaussian beyond sqrt(ln(floor) / ln(c)) pitches (2.2 for c = 0.15), ~14 actuators
        per pixel instead of 672; the thin-plate functions keep ~62 (their modes move by at
        most 0.2 % RMS; a loop frame costs 3-7 % more, ``bench/bench_influence.py``).  For
        the per-frame mirror shape and modal projections of the closed loop;
        ``registration``: the mirror as a mis-registered pyramid sees it
        (``optics.registration``)."""
        x, y = pupil.coordinates()
        p, pitch = self.positions(), self.pitch_m
        if registration is not None:
            p, pitch = registration.positions(p, pitch), registration.pitch(pitch)
        if self.influence == "thin-plate":
            dense = thin_plate_cardinals(np.stack([x, y], axis=1), p, pitch)
            dense[np.abs(dense) < floor] = 0.0
            return csr_matrix(dense)
        radius2 = np.log(floor) / np.log(self.coupling) * pitch**2
        tree = cKDTree(p)
        rows_list: list[int] = []
        cols_list: list[int] = []
        for i, neighbours in enumerate(tree.query_ball_point(np.stack([x, y], axis=1), np.sqrt(radius2))):
            rows_list.extend([i] * len(neighbours))
            cols_list.extend(neighbours)
        rows, cols = np.array(rows_list), np.array(cols_list)
        d2 = (x[rows] - p[cols, 0]) ** 2 + (y[rows] - p[cols, 1]) ** 2
        values = np.exp(np.log(self.coupling) * d2 / pitch**2)
        return csr_matrix((values, (rows, cols)), shape=(x.size, self.n_actuators))

    def influence_functions(self, pupil: Pupil) -> np.ndarray:
        """(n_valid_pixels, n_actuators): each actuator's unit response on the pupil pixels."""
        x, y = pupil.coordinates()
        p = self.positions()
        if self.influence == "thin-plate":
            return thin_plate_cardinals(np.stack([x, y], axis=1), p, self.pitch_m)
        d2 = (x[:, None] - p[None, :, 0]) ** 2 + (y[:, None] - p[None, :, 1]) ** 2
        return np.exp(np.log(self.coupling) * d2 / self.pitch_m**2)


def check_influence(influence: str) -> None:
    """InputError unless ``influence`` names one of the influence-function models."""
    if influence not in INFLUENCES:
        raise InputError(f"mirror.influence must be one of {', '.join(INFLUENCES)}, got {influence!r}")


def _thin_plate_kernel(r: np.ndarray) -> np.ndarray:
    """r^2 ln r (0 at r = 0): the biharmonic Green's function of an unbounded thin plate."""
    out = np.zeros_like(r)
    np.multiply(r**2, np.log(r, where=r > 0, out=np.ones_like(r)), out=out, where=r > 0)
    return out


@blas.on_one_thread
def thin_plate_cardinals(points: np.ndarray, actuators: np.ndarray, scale: float) -> np.ndarray:
    """(n_points, n_actuators): at ``points`` (x, y), the thin-plate spline through 1 at each
    actuator and 0 at the others (kernel r^2 ln r plus an affine part whose weights are
    orthogonal to it, Duchon 1977); lengths in units of ``scale`` for the conditioning."""
    a = actuators / scale
    n = len(a)
    A = np.zeros((n + 3, n + 3))
    A[:n, :n] = _thin_plate_kernel(np.hypot(a[:, None, 0] - a[None, :, 0], a[:, None, 1] - a[None, :, 1]))
    A[:n, n:] = np.column_stack([np.ones(n), a])
    A[n:, :n] = A[:n, n:].T
    weights = np.linalg.solve(A, np.vstack([np.eye(n), np.zeros((3, n))]))
    q = points / scale
    kernel = _thin_plate_kernel(np.hypot(q[:, None, 0] - a[None, :, 0], q[:, None, 1] - a[None, :, 1]))
    return kernel @ weights[:n] + np.column_stack([np.ones(len(q)), q]) @ weights[n:]


@dataclass(frozen=True)
class ModalBasis:
    """Modes-to-commands ``M`` (n_actuators x n_modes) and its inverse ``M_inv``.

    ``variance`` is each mode's turbulent variance (rad^2 at 500 nm for r0 = 1 m; Tip/Tilt
    included), the ordering key of the KL modes."""

    M: np.ndarray
    M_inv: np.ndarray
    variance: np.ndarray
    geometry: AsmGeometry
    L0_m: float

    @property
    def n_modes(self) -> int:
        return self.M.shape[1]

    def truncated(self, n_modes: int) -> ModalBasis:
        if not (1 <= n_modes <= self.n_modes):
            raise InputError(f"modes must be in 1..{self.n_modes} for this mirror, got {n_modes}")
        return ModalBasis(self.M[:, :n_modes], self.M_inv[:n_modes], self.variance[:n_modes], self.geometry, self.L0_m)

    def shapes(self, pupil: Pupil) -> np.ndarray:
        """(n_valid_pixels, n_modes) mode shapes on ``pupil`` (OPD per unit coefficient)."""
        return self.geometry.influence_functions(pupil) @ self.M


def _covariance_kernel(pupil: Pupil, L0_m: float) -> np.ndarray:
    """Phase covariance C(x - x') on the (2n)^2 grid of separations, FFT-ready (r0 = 1 m)."""
    n = pupil.n_pixels
    k = np.fft.fftfreq(2 * n, 1.0 / (2 * n)) * pupil.pixel_scale_m
    r = np.hypot(*np.meshgrid(k, k))
    return phase_covariance(r, 1.0, L0_m)


def covariance_applied(functions: np.ndarray, pupil: Pupil, L0_values) -> list[np.ndarray]:
    """C f for each L0: the von Karman phase covariance (rad^2 at 500 nm, r0 = 1 m) applied to
    pupil functions (n_valid_pixels, k) by FFT convolution on the doubled grid (no wrap-around);
    the functions' transform is computed once for all the L0 values."""
    n = pupil.n_pixels
    rows, cols = np.nonzero(pupil.mask)
    images = np.zeros((functions.shape[1], 2 * n, 2 * n))
    images[:, rows, cols] = functions.T
    spectra = scipy.fft.rfft2(images, workers=-1)
    out = []
    for L0 in L0_values:
        kernel = scipy.fft.rfft2(_covariance_kernel(pupil, L0))
        out.append(scipy.fft.irfft2(spectra * kernel, s=(2 * n, 2 * n), workers=-1)[:, rows, cols].T)
    return out


@dataclass(frozen=True)
class MirrorSpace:
    """The mirror's functions in whitened coordinates: ``W`` maps them to actuator commands
    (F W orthonormal on the pupil), ``G`` is the pupil Gram matrix of the influence functions,
    ``K`` the von Karman covariance there (rad^2 at 500 nm, r0 = 1 m), ``piston`` the mirror's
    least-squares piston, ``tip_tilt`` the mirror's least-squares Tip and Tilt (two
    columns), ``turbulence`` the piston-removed variance of the turbulence on the pupil (the
    same units)."""

    W: np.ndarray
    G: np.ndarray
    K: np.ndarray
    piston: np.ndarray
    tip_tilt: np.ndarray
    turbulence: float


def mirror_space(geometry: AsmGeometry, pupil: Pupil, L0_m: float, eigen_floor: float = 1e-6) -> MirrorSpace:
    """The whitened mirror space and its turbulence covariance (F^T C F / n_p^2 by FFT convolution)."""
    F = geometry.influence_functions(pupil)
    n_p = F.shape[0]
    G = F.T @ F / n_p
    s, U = np.linalg.eigh(G)
    keep = s > eigen_floor * s.max()
    W = U[:, keep] / np.sqrt(s[keep])  # whitening: F W has orthonormal columns (mean-square)
    CF = covariance_applied(F, pupil, (L0_m,))[0]  # (n_p, n_act): C applied to each influence function
    C1 = covariance_applied(np.ones((n_p, 1)), pupil, (L0_m,))[0]  # and to piston
    K = W.T @ (F.T @ CF) @ W / n_p**2
    piston = (W.T @ (F.T @ np.ones((n_p, 1))) / n_p)[:, 0]
    tip_tilt = W.T @ (F.T @ np.stack(pupil.tilt(), axis=1)) / n_p
    turbulence = float(phase_covariance(np.zeros(1), 1.0, L0_m)[0] - C1.sum() / n_p**2)
    return MirrorSpace(W, G, K, piston, tip_tilt, turbulence)


def best_fitting_variance(space: MirrorSpace, n_modes: int) -> float:
    """The turbulence variance no n_modes-dimensional subspace of the mirror fits better: the
    piston-removed variance less the n_modes largest eigenvalues of K without piston (the
    bound ``kl_basis``'s modes are measured against; rad^2 at 500 nm for r0 = 1 m)."""
    u = space.piston / np.linalg.norm(space.piston)
    P = np.eye(space.K.shape[0]) - np.outer(u, u)
    evals = np.sort(np.linalg.eigvalsh(P @ space.K @ P))[::-1]
    return space.turbulence - float(evals[:n_modes].sum())


def canonical_signs(modes_w: np.ndarray, W: np.ndarray) -> np.ndarray:
    """``modes_w`` (whitened coordinates, one mode per column) with each sign chosen so that
    the mode's actuator commands ``W m`` project positively on a seeded generic vector: a rule
    that no symmetry of the mirror ties ("largest coefficient positive" does for modes whose
    extremes are equal and opposite) and that roundoff cannot flip."""
    generic = np.random.default_rng(SIGN_SEED).standard_normal(W.shape[0])
    projection = generic @ (W @ modes_w)
    return modes_w * np.where(projection < 0, -1.0, 1.0)


@blas.on_one_thread  # the same basis on every machine
def kl_basis(geometry: AsmGeometry, pupil: Pupil, L0_m: float = defaults.L0_M, eigen_floor: float = 1e-6) -> ModalBasis:
    """Tip/Tilt + KL modes of the mirror on ``pupil`` (see the module docstring)."""
    if not (L0_m > 0 and np.isfinite(L0_m)):
        raise InputError(f"outer scale L0 for the KL modes must be a finite number > 0 m, got {L0_m}")
    space = mirror_space(geometry, pupil, L0_m, eigen_floor)
    W, K, tt = space.W, space.K, space.tip_tilt
    # Piston first, then the mirror's Tip and Tilt, orthonormalised in that order.
    Q, _ = np.linalg.qr(np.concatenate([space.piston[:, None], tt], axis=1))
    Q = Q * np.sign(np.diag(Q.T @ np.concatenate([space.piston[:, None], tt], axis=1)))
    P = np.eye(K.shape[0]) - Q @ Q.T
    evals, evecs = np.linalg.eigh(P @ K @ P)
    order = np.argsort(evals)[::-1][: K.shape[0] - 3]
    kl = canonical_signs(evecs[:, order], W)
    modes_w = np.concatenate([Q[:, 1:3], kl], axis=1)
    variance = np.einsum("im,ij,jm->m", modes_w, K, modes_w)
    M = W @ modes_w
    M_inv = M.T @ space.G
    return ModalBasis(M=M, M_inv=M_inv, variance=variance, geometry=geometry, L0_m=L0_m)
