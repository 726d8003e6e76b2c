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


LONGEST_FIRST = ("tests/test_readme.py::test_readme_examples_run_in_order",)  # ~7 min in one process


def pytest_collection_modifyitems(items):
    """The longest tests first, so that pytest-xdist's work stealing balances the rest around
    them instead of waiting for one at the end."""
    items.sort(key=lambda item: item.nodeid not in LONGEST_FIRST)
