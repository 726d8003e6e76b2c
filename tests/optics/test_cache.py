"""The calibration cache: an entry is used only when it holds the arrays its caller expects,
finite, with a matching checksum; any other entry is recomputed and overwritten."""

import shutil

import numpy as np
import pytest

from soulctl.loop.chi_model import optical_gain_table
from soulctl.optics.asm import AsmGeometry
from soulctl.optics.cache import CHECKSUM, ArrayCache, EntrySpec, checksum
from soulctl.optics.calibration import BasisSetup, CalibrationSetup, basis_entry, calibrate, modal_basis
from soulctl.optics.pwfs import PyramidConfig

SETUP = CalibrationSetup(PyramidConfig(binning=4, oversampling=1), 10)


def seeded(folder, optics_cache) -> ArrayCache:
    """A cache in ``folder`` holding the session's basis (computed once per session)."""
    modal_basis(BasisSetup(), optics_cache)
    key = BasisSetup().key()
    shutil.copy(optics_cache.path(key), folder / f"{key}.npz")
    return ArrayCache(folder)


@pytest.fixture(scope="module")
def fresh(tmp_path_factory, optics_cache):
    """A calibration of SETUP computed from scratch (on the session's basis)."""
    cal = calibrate(SETUP, seeded(tmp_path_factory.mktemp("fresh"), optics_cache))
    assert not cal.from_cache
    return cal


@pytest.fixture
def cache(tmp_path, optics_cache, fresh):
    """A cache holding the basis and a valid calibration entry of SETUP."""
    c = seeded(tmp_path, optics_cache)
    assert not calibrate(SETUP, c).from_cache and calibrate(SETUP, c).from_cache
    return c


def entry(cache, key):
    with np.load(cache.path(key)) as data:
        return {name: data[name] for name in data.files}


def assert_fresh(cal, fresh):
    for name in ("interaction_matrix", "reconstructor", "reference_slopes"):
        np.testing.assert_array_equal(getattr(cal, name), getattr(fresh, name))


def _keep_checksum(change):
    """Edit the arrays, keep the stored checksum (a zeroed or scaled entry)."""

    def edit(arrays):
        stored = arrays.pop(CHECKSUM)
        change(arrays)
        return {**arrays, CHECKSUM: stored}

    return edit


def _new_checksum(change):
    """Edit the arrays and write a matching checksum (well-formed, but not what the caller expects)."""

    def edit(arrays):
        arrays.pop(CHECKSUM)
        change(arrays)
        return {**arrays, CHECKSUM: np.array(checksum(arrays))}

    return edit


def _set(name, make):
    return lambda arrays: arrays.__setitem__(name, make(arrays[name]))


TAMPERINGS = {
    "zero R": _keep_checksum(_set("R", np.zeros_like)),
    "scale R": _keep_checksum(_set("R", lambda R: 2 * R)),
    "one value of D": _keep_checksum(_set("D", lambda D: np.where(np.arange(D.size).reshape(D.shape) == 7, D + 1e-12, D))),
    "drop a key": _new_checksum(lambda a: a.pop("reference")),
    "an extra key": _new_checksum(lambda a: a.__setitem__("extra", np.ones(3))),
    "wrong shape": _new_checksum(_set("R", lambda R: R[:, :-1])),
    "fewer modes": _new_checksum(lambda a: (a.__setitem__("R", a["R"][:5]), a.__setitem__("D", a["D"][:, :5]))),
    "NaN": _new_checksum(_set("D", lambda D: np.where(D == D.flat[3], np.nan, D))),
    "text instead of numbers": _new_checksum(_set("reference", lambda r: r.astype(str))),
    "no checksum (an older entry)": lambda a: {k: v for k, v in a.items() if k != CHECKSUM},
    "a foreign .npz": lambda a: {"x": np.arange(4.0)},
}


@pytest.mark.parametrize("tamper", TAMPERINGS.values(), ids=TAMPERINGS.keys())
def test_a_tampered_calibration_entry_is_recomputed_and_overwritten(cache, fresh, tamper):
    path = cache.path(SETUP.key())
    np.savez(path, **tamper(entry(cache, SETUP.key())))
    again = calibrate(SETUP, cache)
    assert not again.from_cache
    assert_fresh(again, fresh)
    later = calibrate(SETUP, cache)  # the entry was overwritten with a valid one
    assert later.from_cache
    assert_fresh(later, fresh)


@pytest.mark.parametrize("content", [b"", b"half a file", b"PK\x03\x04" + bytes(100)])
def test_an_unreadable_entry_is_recomputed(cache, fresh, content):
    cache.path(SETUP.key()).write_bytes(content)
    again = calibrate(SETUP, cache)
    assert not again.from_cache
    assert_fresh(again, fresh)


def test_something_else_at_the_entry_path_is_no_entry(cache, fresh):
    path = cache.path(SETUP.key())
    path.unlink()
    path.mkdir()
    again = calibrate(SETUP, cache)  # a miss, and the folder is not replaced
    assert not again.from_cache and path.is_dir()
    assert_fresh(again, fresh)


def test_a_scaled_basis_is_a_miss(cache):
    key = BasisSetup().key()
    np.savez(cache.path(key), **_keep_checksum(_set("M", lambda M: 2 * M))(entry(cache, key)))
    assert cache.load(key, basis_entry(BasisSetup())) is None


def test_a_basis_short_of_modes_is_recomputed_before_the_request_is_blamed(tmp_path):
    """A basis cut to 5 modes with a valid checksum (the right arrays, the wrong count):
    recomputed, not 'modes must be in 1..5 for this mirror'.  A 60-actuator mirror keeps it fast."""
    setup = CalibrationSetup(PyramidConfig(binning=4, oversampling=1), 10, BasisSetup(AsmGeometry(n_actuators=60, n_rings=4), pixels=40))
    fresh = calibrate(setup, ArrayCache(None))
    cache = ArrayCache(tmp_path)
    calibrate(setup, cache)
    key = setup.basis.key()
    cut = _new_checksum(
        lambda a: (a.__setitem__("M", a["M"][:, :5]), a.__setitem__("M_inv", a["M_inv"][:5]), a.__setitem__("variance", a["variance"][:5]))
    )
    np.savez(cache.path(key), **cut(entry(cache, key)))
    cache.path(setup.key()).unlink()
    assert_fresh(calibrate(setup, cache), fresh)
    assert modal_basis(setup.basis, cache).n_modes == 59  # overwritten: Tip/Tilt + KL, piston removed


def test_a_tampered_optical_gain_table_is_recomputed(cache, fresh):
    first = optical_gain_table(fresh, cache)
    key = next(p.stem for p in cache.directory.glob("optical-gains-*.npz"))
    np.savez(cache.path(key), **_keep_checksum(_set("gains", lambda g: 10 * g))(entry(cache, key)))
    np.testing.assert_array_equal(optical_gain_table(fresh, cache), first)
    np.savez(cache.path(key), **_new_checksum(_set("gains", lambda g: g[:-1]))(entry(cache, key)))
    np.testing.assert_array_equal(optical_gain_table(fresh, cache), first)


def test_entry_spec_shapes_and_shared_sizes():
    spec = EntrySpec({"D": ("s", 3), "R": (3, "s")}, {"s": (2, 10)})
    assert spec.matches({"D": (4, 3), "R": (3, 4)})
    assert not spec.matches({"D": (4, 3), "R": (3, 5)})  # s differs
    assert not spec.matches({"D": (11, 3), "R": (3, 11)})  # s beyond its range
    assert not spec.matches({"D": (4, 2), "R": (2, 4)})  # a fixed size differs
    assert not spec.matches({"D": (4, 3)})  # a key missing
    assert not spec.matches({"D": (4, 3), "R": (3, 4), "x": (1,)})  # a key too many


def test_the_checksum_covers_names_dtypes_shapes_and_bytes():
    a = {"x": np.arange(6.0).reshape(2, 3)}
    base = checksum(a)
    assert checksum({"x": a["x"].copy()}) == base
    assert checksum({"y": a["x"]}) != base
    assert checksum({"x": a["x"].astype(np.float32)}) != base
    assert checksum({"x": a["x"].reshape(3, 2)}) != base
    assert checksum({"x": a["x"] * 2}) != base
    assert checksum({"x": np.asfortranarray(a["x"])}) == base  # the values, not the memory layout


def test_entries_land_at_once_not_with_the_commands_outputs(tmp_path):
    """A command whose outputs are discarded (it failed) keeps what it computed."""
    from soulctl.files import staged_outputs

    cache = ArrayCache(tmp_path)
    spec = EntrySpec({"x": (3,)})
    with staged_outputs():  # never committed
        cache.store("k", {"x": np.arange(3.0)})
    np.testing.assert_array_equal(cache.load("k", spec)["x"], np.arange(3.0))
    assert not list(tmp_path.glob(".soulctl-*"))
