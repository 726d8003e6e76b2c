"""The one way the benchmarks write their JSON: the payload with soulctl's version and the
machine it ran on, written atomically (``soulctl.files``), and said on the console."""

from __future__ import annotations

import json
import os
import platform
from pathlib import Path

from soulctl import __version__
from soulctl.files import atomic_write_text


def save(out: Path, payload: dict, console) -> None:
    result = {
        "soulctl": __version__,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "processor": platform.processor()},
        **payload,
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, json.dumps(result, indent=1))
    console.print(f"written {out}")
