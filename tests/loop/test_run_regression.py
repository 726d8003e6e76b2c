"""Every path that builds a closed loop gives the figures it gave before the run description
(tests/regression_runs.py recorded them): loop run with and without options, with the
auxiliary loops, optimize gains live and offline."""

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parents[1]))
from regression_runs import RECORD, close, figures  # noqa: E402


def test_every_run_path_gives_the_recorded_figures(optics_cache):
    recorded = json.loads(RECORD.read_text())["figures"]
    now = figures(str(optics_cache.directory))
    assert now.keys() == recorded.keys()
    for name in recorded:
        assert close(now[name], recorded[name]), (name, now[name], recorded[name])
