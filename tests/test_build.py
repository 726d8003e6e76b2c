"""The build: without Eigen the CMake step stops with one line naming the Debian package."""

import shutil
import subprocess
from pathlib import Path

import pytest

SOURCE = Path(__file__).resolve().parent.parent


@pytest.mark.skipif(not (SOURCE / "CMakeLists.txt").exists() or shutil.which("cmake") is None, reason="needs the source tree and cmake")
def test_missing_eigen_names_the_debian_package(tmp_path):
    proc = subprocess.run(
        ["cmake", "-S", str(SOURCE), "-B", str(tmp_path), "-DCMAKE_DISABLE_FIND_PACKAGE_Eigen3=TRUE"],
        capture_output=True,
        text=True,
    )
    assert proc.returncode != 0
    lines = [line.strip() for line in proc.stderr.splitlines() if "libeigen3-dev" in line]
    assert lines == ["Eigen 3 not found: install Debian package libeigen3-dev"]
