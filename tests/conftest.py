from pathlib import Path

import pytest

from soulctl.optics.cache import ArrayCache


@pytest.fixture(scope="session")
def optics_cache(tmp_path_factory):
    """One on-disk cache for the session: the modal basis is computed once, not per test."""
    return ArrayCache(tmp_path_factory.mktemp("optics-cache"))


@pytest.fixture(scope="session")
def cache_dir(optics_cache):
    """The same cache's folder for the commands' --cache-dir: each configuration is calibrated
    once per session (per xdist worker), not once per test module.  Tests of the cache itself
    make their own."""
    return Path(optics_cache.directory)


@pytest.fixture(scope="session")
def validation(tmp_path_factory):
    """``validation(name)``: the module ``validation.<name>`` of the repository's studies,
    imported as ``python -m validation.<name>`` from the root would import it, but with the
    installed soulctl (a folder holding only a link to validation/ goes first on sys.path, not
    the source tree, whose soulctl has no compiled core)."""
    import importlib
    import sys

    folder = tmp_path_factory.mktemp("validation-path")
    (folder / "validation").symlink_to(Path(__file__).resolve().parents[1] / "validation")
    sys.path.insert(0, str(folder))
    return lambda name: importlib.import_module(f"validation.{name}")


LONGEST_FIRST = ("tests/test_readme.py::test_readme_examples_run_in_order",)  # ~7 min in one process


def pytest_collection_modifyitems(items):
    """The longest tests first, so that pytest-xdist's work stealing balances the rest around
    them instead of waiting for one at the end."""
    items.sort(key=lambda item: item.nodeid not in LONGEST_FIRST)
