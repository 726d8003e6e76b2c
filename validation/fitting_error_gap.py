"""Where the 500-mode fitting gap to a pupil-plane KL basis comes from (fidelity issue, item 2).

For von Karman turbulence (L0 = 25 m, 1" at 500 nm) on the 80-px LBT pupil, the piston-removed
fitting error of n modes, computed from covariances (no screens):

* ``kl_basis``: soulctl's Tip/Tilt + KL modes of the LBT672 model;
* mirror bound: the best n-dimensional subspace of the mirror's functions (the largest
  eigenvalues of the mirror's covariance, ``asm.best_fitting_variance``);
* pupil KL: the best n-dimensional subspace of all pupil functions (the largest eigenvalues of
  the pupil's covariance matrix, 4964 pixels; ~40 s), what a KL basis not limited to a mirror
  reaches.

If soulctl's modes match the mirror bound, the gap to the pupil KL is the mirror model's
(actuator count and layout, influence functions), not the modes'; the mirror bound is then
computed for other Gaussian couplings (0.15 at one pitch is soulctl's proposal), and the whole
table for both influence-function models (``asm.INFLUENCES``: the Gaussian and the thin
plate).  Last, the fitting error the independent comparison with OOPAO measured (500 modes,
examples/oopao_matched.toml's turbulence, on screens) for each model.

    python -m validation.fitting_error_gap [--pixels 80] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import scipy.linalg

from soulctl.optics.asm import INFLUENCES, AsmGeometry, best_fitting_variance, kl_basis, mirror_space
from soulctl.optics.atmosphere import AtmosphereConfig, FrozenFlowAtmosphere, Layer, phase_covariance, r0_from_seeing
from soulctl.optics.pupil import Pupil
from validation.provenance import provenance

OUT = Path(__file__).parent / "results" / "fitting_error_gap.json"
L0_M, SEEING = 25.0, 1.0
MODES = (100, 300, 500, 600, 671)
COUPLINGS = (0.05, 0.15, 0.3, 0.45)
OOPAO_R0_M, OOPAO_L0_M = 0.15, 40.0  # examples/oopao_matched.toml's turbulence
OOPAO_FITTING_NM = 68.2  # OOPAO's 500 KL modes on its own mirror, same turbulence (the independent comparison)


def pupil_kl_variances(pupil: Pupil, n: int) -> np.ndarray:
    """The n largest eigenvalues of the piston-removed von Karman covariance of the pupil's
    pixels (mean-square normalisation, rad^2 at 500 nm for r0 = 1 m)."""
    rows, cols = np.nonzero(pupil.mask)
    xy = np.stack([rows, cols], axis=1) * pupil.pixel_scale_m
    d = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
    C = phase_covariance(d, 1.0, L0_M) / len(rows)
    del d
    C -= C.mean(axis=0, keepdims=True)
    C -= C.mean(axis=1, keepdims=True)
    m = len(rows)
    return scipy.linalg.eigh(C, eigvals_only=True, subset_by_index=[m - n, m - 1])[::-1]


def fitting_table(geometry: AsmGeometry, pupil: Pupil, pupil_kl: np.ndarray, nm: float) -> list[dict]:
    """kl_basis, mirror bound and pupil KL at each of MODES (nm)."""
    basis = kl_basis(geometry, pupil, L0_M)
    space = mirror_space(geometry, pupil, L0_M)
    rows = []
    for n in MODES:
        ours = space.turbulence - float(basis.variance[:n].sum())
        rows.append(
            {
                "modes": n,
                "kl_basis_nm": nm * math.sqrt(ours),
                "mirror_bound_nm": nm * math.sqrt(best_fitting_variance(space, n)),
                "pupil_kl_nm": nm * math.sqrt(space.turbulence - float(pupil_kl[:n].sum())),
            }
        )
    return rows


def screen_fitting_nm(geometry: AsmGeometry, pupil: Pupil, screens: int = 4, positions: int = 10) -> float:
    """The 500-mode fitting error of the OOPAO-matched set-up's turbulence (one layer, r0 =
    0.15 m at 500 nm, L0 = 40 m; examples/oopao_matched.toml) on soulctl's screens, RMS over
    ``screens`` seeds x ``positions`` wind positions: what the independent comparison measured
    (74.9 nm for the Gaussian mirror against OOPAO's 68.2)."""
    shapes = kl_basis(geometry, pupil, OOPAO_L0_M).shapes(pupil)[:, :500]
    total = 0.0
    for seed in range(screens):
        seeing = r0_from_seeing(1.0) / OOPAO_R0_M  # arcsec: the seeing is inversely proportional to r0
        config = AtmosphereConfig(seeing, OOPAO_L0_M, (Layer(0.0, 1.0, 10.0, 0.0),))
        atm = FrozenFlowAtmosphere(config, pupil.n_pixels, pupil.pixel_scale_m, seed)
        for i in range(positions):
            opd = atm.opd_nm(40 * i * pupil.pixel_scale_m / 10.0)  # 40 pixels apart at 10 m/s
            p = opd[pupil.mask] - opd[pupil.mask].mean()
            total += float(np.mean((p - shapes @ (shapes.T @ p / pupil.n_valid)) ** 2))
    return math.sqrt(total / (screens * positions))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--pixels", type=int, default=80)
    p.add_argument("--out", type=Path, default=OUT)
    a = p.parse_args()
    pupil = Pupil(a.pixels)
    pupil_kl = pupil_kl_variances(pupil, max(MODES))
    nm = 500.0 / (2.0 * math.pi) * r0_from_seeing(SEEING) ** (-5 / 6)  # rad at r0 = 1 m -> nm at the seeing
    tables = {model: fitting_table(AsmGeometry(influence=model), pupil, pupil_kl, nm) for model in INFLUENCES}
    gaussians = {c: AsmGeometry(coupling=c, influence="gaussian") for c in COUPLINGS}
    couplings = {c: nm * math.sqrt(best_fitting_variance(mirror_space(g, pupil, L0_M), 500)) for c, g in gaussians.items()}
    screens = {model: screen_fitting_nm(AsmGeometry(influence=model), pupil) for model in INFLUENCES}
    result = {
        "pixels": a.pixels,
        "L0_m": L0_M,
        "seeing_arcsec": SEEING,
        "rows": tables["gaussian"],
        "rows_by_influence": tables,
        "mirror_bound_500_nm_by_coupling": couplings,
        "oopao_matched_screens_500_nm": screens | {"oopao": OOPAO_FITTING_NM},
    }
    a.out.write_text(json.dumps(result | provenance(), indent=1) + "\n")
    for model, rows in tables.items():
        print(f"\n{model}\n| modes | kl_basis nm | mirror bound nm | pupil KL nm | kl_basis / pupil KL |\n|---|---|---|---|---|")
        for r in rows:
            ratio = r["kl_basis_nm"] / r["pupil_kl_nm"]
            print(f"| {r['modes']} | {r['kl_basis_nm']:.1f} | {r['mirror_bound_nm']:.1f} | {r['pupil_kl_nm']:.1f} | {ratio:.3f} |")
    print("\n| coupling at one pitch | mirror bound, 500 modes nm |\n|---|---|")
    for c, v in couplings.items():
        print(f"| {c:g} | {v:.1f} |")
    print("\n| OOPAO-matched screens, 500 modes | nm | / OOPAO's 68.2 |\n|---|---|---|")
    for model, v in screens.items():
        print(f"| {model} | {v:.1f} | {v / OOPAO_FITTING_NM:.3f} |")


if __name__ == "__main__":
    main()
