"""The README and the guide as a test: every command of their ``sh`` and ``python`` blocks runs,
in order (``DOCS``), in one folder, with SOULCTL_QUICK set (``soulctl/cli/quick.py``: the same
command lines at a smoke test's cost), and exits as its comment says (``# exit N``), else 0.

A block after ``<!-- doc-test: skip: REASON -->`` is not run (the reason is required); a block
after ``<!-- doc-test: file NAME -->`` is written to NAME when the README reaches it.  The
blocks marked ``test-command`` (.ci/run runs it) and ``real-record-example``
(tests/telemetry/test_real_records.py runs it) are run by their own tests.  A document whose
blocks the test does not read is a document whose examples may break: ``DOCS`` lists every
Markdown file of the repository that holds a shell block."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = (README, ROOT / "docs" / "guide.md", ROOT / "docs" / "development.md")  # run in this order
MARKER = re.compile(r"^<!-- ?([a-z-]+)(?::\s*|\s+)?(.*?)\s*-->$")
RUN_ELSEWHERE = {"test-command", "real-record-example"}
EXIT = re.compile(r"#\s*exit (\d+)")
REPO_FOLDERS = ("examples", "tables", "tests")  # what README commands read by relative path
TIMEOUT_S = 900


@dataclass(frozen=True)
class Block:
    language: str
    text: str
    line: int  # of its opening fence
    marker: str  # the comment before it: "doc-test: skip", "doc-test: file", "test-command", ...
    argument: str  # the skip reason, the file name


def blocks(text: str) -> list[Block]:
    """The fenced blocks of a Markdown text with the marker comment just before each."""
    out, lines, i = [], text.splitlines(), 0
    while i < len(lines):
        if not lines[i].startswith("```"):
            i += 1
            continue
        language, start = lines[i][3:].strip(), i
        end = next(j for j in range(i + 1, len(lines)) if lines[j].startswith("```"))
        before = next((lines[j].strip() for j in range(i - 1, -1, -1) if lines[j].strip()), "")
        marker, argument = _marker(before)
        out.append(Block(language, "\n".join(lines[i + 1 : end]) + "\n", start + 1, marker, argument))
        i = end + 1
    return out


def _marker(line: str) -> tuple[str, str]:
    m = MARKER.match(line)
    if m is None:
        return "", ""
    kind, rest = m.group(1), m.group(2)
    if kind == "doc-test":
        what, _, argument = rest.partition(":") if rest.startswith("skip") else rest.partition(" ")
        return f"doc-test: {what.strip()}", argument.strip()
    return kind, rest


def commands(block: Block) -> list[tuple[str, int]]:
    """A shell block's commands (continuation lines joined) and the exit status each expects."""
    out, pending = [], ""
    for raw in block.text.splitlines():
        pending += raw.rstrip()
        if pending.endswith("\\"):
            pending = pending[:-1] + " "
            continue
        line, pending = pending.strip(), ""
        if line and not line.startswith("#"):
            m = EXIT.search(line)
            out.append((line, int(m.group(1)) if m else 0))
    return out


def runnable(readme: str) -> list[Block]:
    return [b for b in blocks(readme) if b.marker not in RUN_ELSEWHERE and b.marker != "doc-test: skip"]


def _all_blocks() -> list[tuple[str, Block]]:
    return [(doc.relative_to(ROOT).as_posix(), b) for doc in DOCS for b in blocks(doc.read_text())]


def test_every_example_block_is_run_or_skipped_with_a_reason():
    """No example escapes the test silently: a shell or Python block is run here, by its own
    test, or skipped with a reason; a file block names its file."""
    for doc, b in _all_blocks():
        if b.marker == "doc-test: skip":
            assert b.argument, f"{doc} line {b.line}: a skipped block needs its reason"
        if b.marker == "doc-test: file":
            assert b.argument and "/" not in b.argument, f"{doc} line {b.line}: a file block names its file"
        assert b.language in ("sh", "python", "toml", ""), f"{doc} line {b.line}: a block in '{b.language}' the test cannot run"
    sh = [b for _, b in _all_blocks() if b.language == "sh" and b.marker not in RUN_ELSEWHERE and b.marker != "doc-test: skip"]
    assert len(sh) >= 8 and sum(len(commands(b)) for b in sh) >= 40


def _markdown_files() -> list[Path]:
    """The repository's own Markdown files (git's list where there is one: not a build folder or
    an environment made inside the clone), outside tests/."""
    listed = subprocess.run(["git", "ls-files", "*.md"], cwd=ROOT, capture_output=True, text=True)
    if listed.returncode == 0 and listed.stdout.strip():
        paths = [ROOT / line for line in listed.stdout.splitlines()]
    else:
        paths = [p for p in ROOT.rglob("*.md") if not ({"build", ".git", ".venv", "site-packages"} & set(p.parts))]
    return [p for p in paths if p.is_file() and p.relative_to(ROOT).parts[0] != "tests"]


def test_every_document_with_examples_is_run():
    """Every Markdown file of the repository (outside tests/) that holds a shell block is in DOCS."""
    with_shell = {p.relative_to(ROOT).as_posix() for p in _markdown_files() if "```sh" in p.read_text()}
    assert "README.md" in with_shell and with_shell <= {d.relative_to(ROOT).as_posix() for d in DOCS}


def test_the_parser_reads_markers_continuations_and_exit_statuses():
    text = (
        "<!-- doc-test: skip: needs hosts -->\n```sh\nx\n```\n\n"
        "<!-- doc-test: file g.toml -->\n```toml\na = 1\n```\n"
        "```sh\na \\\n  b  # exit 3\nc\n```\n"
    )
    skip, file, sh = blocks(text)
    assert (skip.marker, skip.argument) == ("doc-test: skip", "needs hosts")
    assert (file.marker, file.argument, file.text) == ("doc-test: file", "g.toml", "a = 1\n")
    assert commands(sh) == [("a    b  # exit 3", 3), ("c", 0)]


def _environment(tmp: Path) -> dict:
    env = dict(os.environ, SOULCTL_QUICK="1", XDG_CACHE_HOME=str(tmp / "cache"), MPLBACKEND="Agg", COLUMNS="100")
    env.pop("PYTHONPATH", None)
    return env


@pytest.mark.slow
def test_readme_examples_run_in_order(tmp_path):
    """Every command of the README and the guide, in order, in one folder (files made by one
    example are read by the next), exits as its comment says."""
    work = tmp_path / "work"
    work.mkdir()
    for name in REPO_FOLDERS:
        (work / name).symlink_to(ROOT / name)
    env, ran = _environment(tmp_path), 0
    for b in (b for doc in DOCS for b in runnable(doc.read_text())):
        if b.marker == "doc-test: file":
            (work / b.argument).write_text(b.text)
        elif b.language == "python":
            result = subprocess.run([sys.executable, "-c", b.text], cwd=work, env=env, capture_output=True, text=True, timeout=TIMEOUT_S)
            _check(result, 0, f"python block at line {b.line}")
            ran += 1
        elif b.language == "sh":
            for command, expected in commands(b):
                argv = ["bash", "-o", "pipefail", "-c", command]
                _check(subprocess.run(argv, cwd=work, env=env, capture_output=True, text=True, timeout=TIMEOUT_S), expected, command)
                ran += 1
    assert ran >= 40


def _check(result: subprocess.CompletedProcess, expected: int, what: str) -> None:
    if result.returncode != expected:
        pytest.fail(f"docs: {what!r} exited {result.returncode}, expected {expected}\n{result.stderr[-3000:]}")
    if expected == 0:
        assert "Traceback" not in result.stderr, (what, result.stderr)


def test_quick_mode_is_said_and_changes_only_cost(tmp_path):
    """SOULCTL_QUICK says on stderr what it changed, and leaves the command line's choices
    (the star, the gains, the field a user gives) as they are."""
    env = _environment(tmp_path)
    argv = ["soulctl", "loop", "run", "--mag", "13", "--duration", "5", "--gains", "0.3,0.2,0.1", "--print-config"]
    out = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=120, check=True)
    assert "SOULCTL_QUICK is set" in out.stderr and "1 s of loop instead of 5 s" in out.stderr
    assert "duration_s = 1.0" in out.stdout and "wfs_field_arcsec = 0.0" in out.stdout and "magnitude_r = 13.0" in out.stdout
    given = subprocess.run([*argv, "--wfs-field", "1.5"], env=env, capture_output=True, text=True, timeout=120, check=True)
    assert "wfs_field_arcsec = 1.5" in given.stdout
    env.pop("SOULCTL_QUICK")
    plain = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=120, check=True)
    assert "SOULCTL_QUICK" not in plain.stderr and "duration_s = 5.0" in plain.stdout
