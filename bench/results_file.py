"""The one way the benchmarks write their JSON: the payload with its provenance (the commit,
soulctl's version, the code fingerprint: ``validation.provenance``) and the machine it ran on,
written atomically (``soulctl.files``), and said on the console."""

from __future__ import annotations

import json
import os
import platform
from pathlib import Path

from soulctl.files import atomic_write_text
from validation.provenance import provenance as study_provenance


def provenance() -> dict:
    """The commit, version and code fingerprint of a benchmark's result, and its machine: the
    studies' record and the cores and platform."""
    record = study_provenance()
    machine = {"cpus": os.cpu_count(), "platform": platform.platform(), "processor": platform.processor()}
    return {**record, "machine": machine | record["machine"]}


def save(out: Path, payload: dict, console) -> None:
    result = {**provenance(), **payload}
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, json.dumps(result, indent=1))
    console.print(f"written {out}")
