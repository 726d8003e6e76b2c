"""Every validation study and benchmark records what made its results (``validation.provenance``,
``bench.results_file``): the commit (``git describe --dirty``), the package version, the code
fingerprint and the machine; and each is a module of its package, run as ``python -m
validation.<study>`` or ``python -m bench.<name>``."""

from __future__ import annotations

import ast
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
STUDIES = ROOT / "validation"


def _studies() -> list[Path]:
    scripts = [*STUDIES.glob("*.py"), *(ROOT / "bench").glob("bench_*.py")]
    return sorted(p for p in scripts if p.name not in ("__init__.py", "provenance.py", "reports.py"))


def test_there_are_studies():
    assert len(_studies()) >= 35  # the walk sees them, so the check below can fail


@pytest.mark.parametrize("path", _studies(), ids=lambda p: p.stem)
def test_every_study_records_its_provenance_and_imports_by_package(path):
    tree = ast.parse(path.read_text())
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name) and n.func.id in ("provenance", "save")]
    assert calls, f"{path.name} writes results without provenance() (or results_file.save)"
    inserted = [n for n in ast.walk(tree) if isinstance(n, ast.Call) and ast.unparse(n.func) == "sys.path.insert"]
    assert not inserted, f"{path.name} edits sys.path: import its siblings as validation.<name>"


def _git(repo: Path, *args: str) -> None:
    subprocess.run(["git", *args], cwd=repo, check=True, capture_output=True)


def test_the_commit_is_git_describe_and_says_dirty(tmp_path, validation):
    provenance = validation("provenance")
    repo = tmp_path / "repo"
    repo.mkdir()
    assert provenance.commit(repo) == "unknown"  # not a checkout
    _git(repo, "init", "-q")
    _git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "--allow-empty", "-m", "one")
    (repo / "f.txt").write_text("a")
    _git(repo, "add", "f.txt")
    _git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "two")
    clean = provenance.commit(repo)
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True, text=True, check=True).stdout.strip()
    assert clean == head[:12]
    (repo / "f.txt").write_text("b")
    assert provenance.commit(repo) == clean + "-dirty"


def test_a_record_holds_commit_version_code_and_machine(validation):
    record = validation("provenance").provenance("abc")
    assert record["code"] == "abc" and record["commit"] and record["version"] and record["machine"]["numpy"]
