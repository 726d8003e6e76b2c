"""Provenance of a validation result: the commit of the source tree that made it (``git
describe --always --dirty``: a result of uncommitted code says "-dirty"), the package version,
the code fingerprint rows of different sessions are joined by, and the machine.  Every result
a validation script writes carries ``provenance()``; ``tests/test_validation_provenance.py``
holds each script to it."""

from __future__ import annotations

import hashlib
import platform
import subprocess
from importlib.metadata import version
from pathlib import Path

import soulctl
from soulctl.tables import tables_dir

REPOSITORY = Path(__file__).resolve().parents[1]


def commit(repository: Path = REPOSITORY) -> str:
    """``git describe --always --dirty --abbrev=12`` of ``repository``; "unknown" outside a
    git checkout (a frozen copy: record its commit where it was made)."""
    try:
        done = subprocess.run(
            ["git", "describe", "--always", "--dirty", "--abbrev=12"], cwd=repository, capture_output=True, text=True, timeout=30
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return done.stdout.strip() if done.returncode == 0 and done.stdout.strip() else "unknown"


def provenance(code: str | None = None) -> dict:
    """What a result row records of what made it: ``code`` (the fingerprint, given when the
    run took it at its start, else now), ``commit``, ``version`` and ``machine``."""
    return {"code": code or code_fingerprint(), "commit": commit(), "version": soulctl.__version__, "machine": machine()}


def code_fingerprint(package: Path | None = None, tables: Path | None = None) -> str:
    """12 hex digits of the SHA-256 of the soulctl sources and tables the rows were made with
    (each .py of the package and each file of its tables, by relative path and content; the
    compiled core is not included).  Rows of different sessions belong in one table when their
    fingerprints agree: the grid takes longer than a session and the code moves between them."""
    h = hashlib.sha256()
    package = package or Path(soulctl.__file__).resolve().parent
    files = [(f"soulctl/{f.relative_to(package)}", f) for f in package.rglob("*.py")]
    files += [(f"tables/{f.name}", f) for f in (tables or tables_dir()).iterdir() if f.is_file()]
    for name, f in sorted(files):
        h.update(name.encode() + b"\0" + f.read_bytes() + b"\0")
    return h.hexdigest()[:12]


def machine() -> dict:
    """What besides the code moves a row's numbers: the libraries pip resolved for the session
    and the CPU's widest vector extension (the core is built with -march=native and OpenBLAS
    picks its kernels per CPU).  A faint loop amplifies a last-bit difference: R14.5 1.0" seed
    2, MGM with OGTL, on one code in two sessions (another machine, the libraries pip resolved
    for each), 0.4003 -> 0.3896 and 0.3968 -> 0.3897 (docs/physics.md, "Over the magnitudes")."""
    flags = next((line.split(":", 1)[1].split() for line in _cpuinfo() if line.startswith("flags")), [])
    simd = next((x for x in ("avx512f", "avx2", "sse4_2") if x in flags), platform.machine())
    return {"simd": simd, **{name: version(name) for name in ("numpy", "scipy")}}


def _cpuinfo() -> list[str]:
    try:
        return Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:  # not Linux
        return []
