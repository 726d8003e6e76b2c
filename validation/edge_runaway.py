"""What the RTC sees of a loop lost during an optimisation: one grid point's own run
(`optimize gains`' closing, OGTL's settling, *before*, the optimisation and *after*; no paired
evaluation), every frame streamed to a telemetry sink and summed per STEP_S.

Per step: the residual's RMS and its Tip/Tilt (the simulation's truth); the residual's controlled
part (``shapes @ residual_modes``) in the pupil's inner half (r < 0.5) and in its edge ring
(r > 0.95); what the RTC has: the pyramid's pupil-mean signal at unit k (the mean of the x and
the y slopes divided by k: with the global normalisation the flux imbalance between the four
pupils, +-1 when saturated), the slopes' RMS at unit k and the RMS over the sub-apertures of
their mean over the step, the safety net's c (the commands of modes 3 and up, sqrt of the sum
of squares), c in the interaction matrix's least sensitive directions, the largest actuator
command, and the sub-apertures' flux map (``FluxMap``); and the net's restores.

Found at R11.9 1.5" seed 3 (mgm+ogtl), where the earlier reading of a lost Tip
(``lock_loss.py``) was wrong: the residual that grows is a shape of the pupil's edge ring,
whose projection on Tip is large, while the pyramid's mean signal stays at zero
(docs/physics.md, "Over the magnitudes").  ~5 min per point on one core at R11.9.

Run:  python -m validation.edge_runaway --mag 11.9 --seeing 1.5 --seed 3 [--out FILE]
"""

from __future__ import annotations

import json

import numpy as np

from soulctl.files import atomic_write_text
from soulctl.loop.auxloops import summary
from soulctl.loop.optimize import OptimizeResult, _live_phases, band_wavelength
from soulctl.loop.simulation import LoopDiverged
from validation.optimize_magnitudes import point_arguments, point_loops
from validation.provenance import provenance

STEP_S = 0.4  # the path's sampling
EDGE_R, INNER_R = 0.95, 0.5  # the edge ring and the inner half, in pupil radii
EVERY = 5  # frames between two projections of the residual on the pupil
WEAK = 0.1  # the interaction matrix's least sensitive directions: this fraction of its singular values
RIM_SUBAPERTURES = 0.9  # the rim's sub-apertures: beyond this fraction of the farthest one's distance
HALF_WAVE_NM = 375.0  # half the sensing wavelength (750 nm): the largest OPD step between two pixels the sampling holds


class FluxMap:
    """The sub-apertures' flux (the sum of the four pupil images, which the slopes' differences
    leave out), summed per frame as the sensor reads it: ``read`` wraps the loop's sensor's
    ``slopes_of_frame`` on that instance.  ``take`` returns, since its last call, the flux in
    the rim's sub-apertures (those beyond RIM_SUBAPERTURES of the farthest) over the
    unaberrated beam's, and the share of the frame's flux in the valid sub-apertures."""

    def __init__(self, sensor):
        self.pixels = sensor.pyramid.subaperture_pixels
        rows, cols = self.pixels[:, 3, 0], self.pixels[:, 3, 1]
        distance = np.hypot(rows - rows.mean(), cols - cols.mean())
        self.rim = distance > RIM_SUBAPERTURES * distance.max()
        reference = self._sums(sensor.expected_frame_of(sensor.pyramid.reference_intensity))
        self.rim_reference = reference[self.rim].sum() / reference.sum()
        self._rim = self._valid = self._total = 0.0
        self._slopes_of_frame = sensor.slopes_of_frame
        sensor.slopes_of_frame = self.read

    def _sums(self, frame: np.ndarray) -> np.ndarray:
        return sum(frame[self.pixels[:, q, 0], self.pixels[:, q, 1]] for q in range(4)).astype(np.float64)

    def read(self, frame: np.ndarray) -> np.ndarray:
        sums = self._sums(frame)
        self._rim += sums[self.rim].sum()
        self._valid += sums.sum()
        self._total += float(frame.sum())
        return self._slopes_of_frame(frame)

    def take(self) -> dict:
        out = {
            "rim_flux_ratio": self._rim / max(self._valid, 1e-30) / self.rim_reference,
            "valid_flux_share": self._valid / max(self._total, 1e-30),
        }
        self._rim = self._valid = self._total = 0.0
        return out


class PathSink:
    """A telemetry sink summing each frame's records per step (``Sink``)."""

    def __init__(
        self, step: int, rate_hz: float, shapes: np.ndarray, radius: np.ndarray, weak: np.ndarray, flux: FluxMap, pairs: np.ndarray
    ):
        self.step, self.rate_hz = step, rate_hz
        self.shapes, self.weak, self.flux = shapes, weak, flux
        self.edge, self.inner = radius > EDGE_R, radius < INNER_R
        self.pairs = pairs[self.edge[pairs[:, 0]] | self.edge[pairs[:, 1]]]  # neighbouring pixels touching the edge ring
        self.rows: list[dict] = []
        self._sums: dict[str, float] = {}
        self._n = self._m = 0
        self._slopes: np.ndarray | None = None  # the step's sum of slopes at unit k

    def attach(self, recorder) -> None:
        pass

    def _add(self, **values: float) -> None:
        for name, v in values.items():
            self._sums[name] = self._sums.get(name, 0.0) + v

    def append(self, frame: int, values: dict) -> None:
        k = float(values["sensitivity"])
        s = np.asarray(values["slopes"], dtype=np.float64) / k
        half = s.size // 2
        r = np.asarray(values["residual_modes"], dtype=np.float64)
        c = np.asarray(values["command_modes"], dtype=np.float64)
        self._add(
            residual2=float(values["residual_rms_nm"]) ** 2,
            tip=r[0],
            tilt=r[1],
            tip2=r[0] ** 2,
            sx=float(s[:half].mean()),
            sy=float(s[half:].mean()),
            slopes2=float(np.mean(s**2)),
            c2=float(np.sum(c[2:] ** 2)),
            c_weak2=float(np.sum((self.weak[:, 2:] @ c[2:]) ** 2)),
        )
        self._slopes = s if self._slopes is None else self._slopes + s
        self._sums["peak"] = max(self._sums.get("peak", 0.0), float(np.max(np.abs(values["commands"]))))
        self._n += 1
        if frame % EVERY == 0:
            opd = self.shapes @ r
            steps = np.abs(opd[self.pairs[:, 0]] - opd[self.pairs[:, 1]])
            self._add(
                edge2=float(np.mean(opd[self.edge] ** 2)),
                inner2=float(np.mean(opd[self.inner] ** 2)),
                modes2=float(r @ r),
                weak2=float(np.sum((self.weak @ r) ** 2)),
                steep=float(np.mean(steps > HALF_WAVE_NM)),
                step_median=float(np.median(steps)),
            )
            self._m += 1
        if self._n == self.step:
            self._close(frame + 1, k)

    def _close(self, frame: int, k: float) -> None:
        n, m, x = self._n, max(self._m, 1), self._sums
        self.rows.append(
            {
                "t_s": frame / self.rate_hz,
                "k": k,
                "residual_nm": np.sqrt(x["residual2"] / n),
                "tip_mean_nm": x["tip"] / n,
                "tilt_mean_nm": x["tilt"] / n,
                "tip_rms_nm": np.sqrt(x["tip2"] / n),
                "inner_nm": np.sqrt(x.get("inner2", 0.0) / m),
                "edge_nm": np.sqrt(x.get("edge2", 0.0) / m),
                "weak_fraction": x.get("weak2", 0.0) / max(x.get("modes2", 0.0), 1e-30),
                "edge_step_median_nm": x.get("step_median", 0.0) / m,
                "edge_steps_over_half_wave": x.get("steep", 0.0) / m,
                "signal_x": x["sx"] / n,
                "signal_y": x["sy"] / n,
                "slopes_rms": np.sqrt(x["slopes2"] / n),
                "mean_slopes_rms": float(np.sqrt(np.mean((self._slopes / n) ** 2))) if self._slopes is not None else 0.0,
                "net_c_nm": np.sqrt(x["c2"] / n),
                "c_weak_nm": np.sqrt(x["c_weak2"] / n),
                "actuator_peak_nm": x["peak"],
                **self.flux.take(),
            }
        )
        self._sums, self._n, self._m, self._slopes = {}, 0, 0, None


def weak_directions(interaction_matrix: np.ndarray) -> tuple[np.ndarray, dict]:
    """(n_weak, n_modes): the right singular vectors of the interaction matrix with the WEAK
    fraction of smallest singular values, the modal directions the pyramid sees least; and
    the singular values that bound them (slopes per nm)."""
    _, sv, vt = np.linalg.svd(np.asarray(interaction_matrix, dtype=np.float64), full_matrices=False)
    n = max(1, round(WEAK * vt.shape[0]))
    return vt[-n:], {"largest": float(sv[0]), "weak_largest": float(sv[-n]), "smallest": float(sv[-1]), "weak": n}


def neighbour_pairs(pupil) -> np.ndarray:
    """(n_pairs, 2) indices, among the valid pupil pixels, of the pairs of horizontal or
    vertical neighbours."""
    index = np.full(pupil.mask.shape, -1)
    index[pupil.mask] = np.arange(int(pupil.mask.sum()))
    pairs = [np.c_[index[:, :-1].ravel(), index[:, 1:].ravel()], np.c_[index[:-1].ravel(), index[1:].ravel()]]
    both = np.concatenate(pairs)
    return both[(both >= 0).all(axis=1)]


def pupil_radius(pupil) -> np.ndarray:
    """Each valid pupil pixel's distance from the centre, in pupil radii."""
    x, y = pupil.coordinates()
    return np.hypot(x, y) / (pupil.diameter_m / 2)


def live_phases(point) -> tuple[OptimizeResult, dict | None]:
    """The point's live phases on its session's loop (``optimize._live_phases``: closing, OGTL's
    settling, *before*, the optimisation, *after*): the result (its phases) and where the loop
    diverged, None if it did not."""
    s, request = point.session, point.request
    initial = s.loop.rtc_parameters.gains
    result = OptimizeResult(request, initial, initial, None, None, s.loop, None)
    try:
        _live_phases(s, result, band_wavelength(request.run.band), None)
    except LoopDiverged as e:
        return result, {"frame": e.frame, "residual_nm": e.residual_nm}
    return result, None


def run_path(mag: float, seeing: float, seed: int, variant: str, wfs_field: float) -> dict:
    """The run's live phases at the point, its path per STEP_S and the net's restores."""
    point = point_loops(mag, seeing, seed, variant, wfs_field=wfs_field)
    request, loop = point.request, point.session.loop
    rate = request.run.observation.frame_rate_hz
    weak, singular = weak_directions(point.cal.interaction_matrix)
    flux = FluxMap(loop.sensor)
    shapes, pupil = point.cal.basis.shapes(loop.pupil), loop.pupil
    sink = PathSink(request.frames(STEP_S), rate, shapes, pupil_radius(pupil), weak, flux, neighbour_pairs(pupil))
    loop.telemetry.sink = sink
    result, diverged = live_phases(point)
    records = summary({name: loop.telemetry.aux_arrays(name) for name in loop.telemetry.aux})
    restored = [f / rate for f in records.get("safety", {}).get("restored_at_frames", [])]
    phases = {k: [f / rate for f in v] for k, v in result.phases.items()}
    return {"phases_s": phases, "singular_values": singular, "path": sink.rows, "restores_s": restored, "diverged": diverged}


def line(row: dict) -> str:
    """One step of the path, printed."""
    return (
        f"{row['t_s']:5.1f} s  k {row['k']:.2f}  residual {row['residual_nm']:5.0f}  Tip {row['tip_mean_nm']:+6.0f}  "
        f"inner {row['inner_nm']:5.0f}  edge {row['edge_nm']:5.0f} (steps {row['edge_step_median_nm']:4.0f}, "
        f"{row['edge_steps_over_half_wave']:.2f} > lambda/2)  weak {row['weak_fraction']:.2f}  "
        f"signal {row['signal_x']:+.3f} {row['signal_y']:+.3f}  mean slopes {row['mean_slopes_rms']:.3f}  "
        f"c {row['net_c_nm']:5.0f}  c weak {row['c_weak_nm']:5.0f}  peak {row['actuator_peak_nm']:6.0f}  "
        f"rim flux {row['rim_flux_ratio']:.3f}  in sub-apertures {row['valid_flux_share']:.3f}"
    )


def main() -> None:
    p = point_arguments(__doc__)
    a = p.parse_args()
    out = {"mag": a.mag, "seeing": a.seeing, "seed": a.seed, "variant": a.variant, "wfs_field_arcsec": a.wfs_field}
    out |= {**provenance()}
    out |= run_path(a.mag, a.seeing, a.seed, a.variant, a.wfs_field)
    for row in out["path"]:
        print(line(row), flush=True)
    print(f"restores at {out['restores_s']} s; diverged {out['diverged']}")
    if a.out:
        atomic_write_text(a.out, json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
