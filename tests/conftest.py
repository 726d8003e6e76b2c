import pytest

from soulctl.optics.cache import ArrayCache


@pytest.fixture(scope="session")
def optics_cache(tmp_path_factory):
    """One on-disk cache for the session: the modal basis is computed once, not per test."""
    return ArrayCache(tmp_path_factory.mktemp("optics-cache"))
