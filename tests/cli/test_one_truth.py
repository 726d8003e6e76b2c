"""One run, one number per figure: `loop run`'s table, its --json, the legend of its
jitter.png and `telemetry psd` on its telemetry file give the same Tip/Tilt jitters (residual
and pseudo-open loop, whole band and above 3 Hz), to the printed digits; the window and the
resolution are stated with them (``soulctl.telemetry.figures``)."""

from __future__ import annotations

import json
import re

import pytest
from cheap import CHEAP_PYRAMID
from cli_run import run

from soulctl.telemetry.figures import mas_text

RUNS = {
    "bright IIR": ["--mag", "14.51", "--tt-control", "iir", "--duration", "0.5"],
    "integrator": ["--mag", "14.51", "--tt-control", "int", "--gains", "0.2,0.26,0.21", "--duration", "0.5"],
    "faint, MGM + OGTL": ["--mag", "16.5", "--duration", "2.5", "--mgm", "--ogtl", "--period", "0.7"],
}


def _run(argv, capsys) -> str:
    status, out, err = run(argv, capsys)
    assert status == 0, err
    return out


def _legends(monkeypatch) -> dict:
    """The labels of every jitter.png legend drawn, captured from the figure."""
    from soulctl.plots import loop as plots

    seen: dict = {}
    draw = plots.jitter_figure

    def capture(jitters, title):
        fig = draw(jitters, title)
        seen["labels"] = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
        return fig

    monkeypatch.setattr(plots, "jitter_figure", capture)
    return seen


def _table_value(out: str, label: str) -> str:
    """The value cell of the table row whose label starts with ``label`` (rows may wrap)."""
    text = " ".join(out.split())
    match = re.search(re.escape(label) + r"[^│]*│\s*([^│]+?)\s*│", text)
    assert match, (label, out)
    return match.group(1)


@pytest.mark.slow
@pytest.mark.parametrize("name", list(RUNS))
def test_loop_run_table_json_plot_and_psd_agree(name, tmp_path, capsys, monkeypatch, cache_dir):
    common = ["loop", "run", *RUNS[name], *CHEAP_PYRAMID, "--seed", "5", "--cache-dir", cache_dir]
    legends = _legends(monkeypatch)
    monkeypatch.setenv("COLUMNS", "200")  # table rows on one line each
    table = _run([*common, "--telemetry", tmp_path / "run.h5", "--plot", tmp_path / "out"], capsys)
    m = json.loads(_run([*common, "--json"], capsys))["metrics"]
    psd = json.loads(_run(["telemetry", "psd", tmp_path / "run.h5", "--pseudo-open-loop", "--json"], capsys))

    res, pol, pol3 = m["tt_jitter_mas"], m["tt_jitter_pol_mas"], m["tt_jitter_pol_3hz_mas"]
    assert mas_text(res) == mas_text(psd["tt_jitter_mas"]["residual_modes"])
    assert mas_text(pol) == mas_text(psd["tt_jitter_mas"]["pseudo_open_loop"])
    assert mas_text(pol3) == mas_text(psd["tt_jitter_above_3hz_mas"]["pseudo_open_loop"])
    assert psd["window_frames"] == [m["skipped_frames"], m["frames"]]
    assert psd["tt_jitter"]["pseudo_open_loop"]["resolution_hz"] == pytest.approx(m["jitter_resolution_hz"])

    assert _table_value(table, "Tip/Tilt jitter per axis, residual") == f"{mas_text(res)} mas"
    assert _table_value(table, "Tip/Tilt jitter per axis, pseudo-open loop").startswith(f"{mas_text(pol)} mas /")
    assert f"{m['jitter_resolution_hz']:.3g} Hz bins" in " ".join(table.split())
    assert legends["labels"] == [f"pseudo-open loop: {mas_text(pol)} mas", f"residual (true wavefront): {mas_text(res)} mas"]
