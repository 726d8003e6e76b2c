"""`loop run --config/--print-config`: the run description on the command line, and a run
repeated from its telemetry file."""

import json
import tomllib
from pathlib import Path

import pytest
from cheap import CHEAP_PYRAMID

from soulctl.cli.app import main
from soulctl.run_config import RunConfig, read_run_config

SMALL = ["--mag", "16.5", *CHEAP_PYRAMID, "--seed", "5"]
EXAMPLES = sorted((Path(__file__).parents[2] / "examples").glob("*.toml"))


def run(args, capsys, cache_dir):
    status = main([*args, "--cache-dir", str(cache_dir)])
    out, err = capsys.readouterr()
    return status, out, err


@pytest.mark.slow
@pytest.mark.parametrize(
    "options",
    [
        ["--duration", "0.3", "--seeing", "0.8", "--wind", "12", "--no-resonance", "--tt-control", "int", "--gains", "0.3,0.4,0.2"],
        ["--duration", "2", "--mgm", "--ogtl", "--period", "0.7", "--probe-mode", "10"],
    ],
    ids=["options", "mgm+ogtl"],
)
def test_a_run_repeated_from_its_telemetry_gives_the_same_numbers(options, tmp_path, capsys, cache_dir):
    h5 = tmp_path / "t.h5"
    status, out, err = run(["loop", "run", *SMALL, *options, "--telemetry", str(h5), "--json"], capsys, cache_dir)
    assert status == 0, err
    status, again, err = run(["loop", "run", "--config", str(h5), "--json"], capsys, cache_dir)
    assert status == 0, err
    first, second = json.loads(out), json.loads(again)
    assert second["metrics"] == first["metrics"] and second.get("final_gains") == first.get("final_gains")
    assert second["configuration"] == first["configuration"]
    stored = read_run_config(h5)
    assert stored.auxiliary.probe_mode == (10 if "--mgm" in options else 30) and stored.seed == 5


def test_print_config_is_the_run_the_options_describe(tmp_path, capsys, cache_dir):
    options = ["loop", "run", *SMALL, "--duration", "0.3", "--seeing", "0.7", "--no-vibrations"]
    status, toml_text, err = run([*options, "--print-config"], capsys, cache_dir)
    assert status == 0, err
    c = RunConfig.from_dict(tomllib.loads(toml_text))
    assert (c.atmosphere.seeing_arcsec, c.vibrations, c.seed, c.duration_s) == (0.7, None, 5, 0.3)
    assert len(c.controller.gains) == 3  # resolved: the gains the run starts from
    path = tmp_path / "run.toml"
    path.write_text(toml_text)
    _, by_options, _ = run([*options, "--json"], capsys, cache_dir)
    status, by_file, err = run(["loop", "run", "--config", str(path), "--json"], capsys, cache_dir)
    assert status == 0, err
    assert json.loads(by_file)["metrics"] == json.loads(by_options)["metrics"]
    # options override the file's fields, the others stay
    status, out, _ = run(["loop", "run", "--config", str(path), "--seeing", "1.2", "--print-config", "--json"], capsys, cache_dir)
    d = json.loads(out)
    assert d["atmosphere"]["seeing_arcsec"] == 1.2 and d["vibrations"] == {"enabled": False} and d["run"]["seed"] == 5


@pytest.mark.parametrize(
    "text, words",
    [
        ("[atmosphere]\nseeing = 1.0\n", "unknown key 'seeing'"),
        ("[run]\nseed = -1\n", "run.seed"),
        ("[control]\ngains = [0.1, 20.0, 0.1]\n", "control.gains"),
        ("[delay]\nframes = 20\n", "1..10"),
        ("[star\n", "TOML"),
    ],
)
def test_a_bad_description_is_one_line_and_writes_nothing(text, words, tmp_path, capsys, cache_dir):
    path, h5 = tmp_path / "bad.toml", tmp_path / "t.h5"
    path.write_text(text)
    status, out, err = run(["loop", "run", "--config", str(path), "--telemetry", str(h5)], capsys, cache_dir)
    assert status == 2 and words in err and err.count("\n") == 1 and out == ""
    assert not h5.exists()


def test_the_textbook_example_carries_none_of_the_sky_like_error_terms(capsys, cache_dir):
    """examples/oopao_matched.toml is the cross-check against another simulator's textbook
    set-up: with --ideal it is the same run (it carried the 100 nm NCPA default once that
    default came, and its Strehl fell with it)."""
    path = next(p for p in EXAMPLES if p.stem == "oopao_matched")
    _, plain, _ = run(["loop", "run", "--config", str(path), "--print-config", "--json"], capsys, cache_dir)
    status, ideal, err = run(["loop", "run", "--config", str(path), "--ideal", "--print-config", "--json"], capsys, cache_dir)
    assert status == 0, err
    assert json.loads(plain) == json.loads(ideal)


@pytest.mark.parametrize("path", EXAMPLES, ids=[p.stem for p in EXAMPLES])
def test_every_example_is_a_valid_run_description(path, capsys, cache_dir):
    status, out, err = run(["loop", "run", "--config", str(path), "--print-config"], capsys, cache_dir)
    assert status == 0, err
    assert RunConfig.from_dict(tomllib.loads(out)) == read_run_config(path).resolved()
