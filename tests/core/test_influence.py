"""The core's influence functions (``_core.InfluenceFunctions``): F c, F^T x and the two in one
pass equal scipy.sparse's CSR products bit for bit, on matrices hypothesis draws (empty rows,
duplicate-free random patterns, sizes around the loop's) and on the mirror's own; F is a
setting (checked at construction, one ValueError per defect naming it); the vectors are data
(NaN propagates, only the dtype and length are refused)."""

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st

from soulctl._core import InfluenceFunctions
from soulctl.optics.asm import AsmGeometry
from soulctl.optics.pupil import Pupil


def core_of(F):
    return InfluenceFunctions(F.indptr, F.indices, F.data, F.shape[1])


def assert_same_as_scipy(F, c, x):
    f = core_of(F)
    shape, seen = f.shape_and_adjoint(c, x)
    expected_shape, expected_seen = F @ c, F.T.tocsr() @ x
    np.testing.assert_array_equal(shape, expected_shape)
    np.testing.assert_array_equal(seen, expected_seen)
    np.testing.assert_array_equal(f.shape(c), expected_shape)
    np.testing.assert_array_equal(f.adjoint(x), expected_seen)


@settings(max_examples=60, deadline=None)
@given(
    n_pixels=st.integers(1, 300),
    n_actuators=st.integers(1, 80),
    density=st.floats(0.0, 1.0),
    seed=st.integers(0, 2**32 - 1),
)
def test_the_products_are_scipys_bit_for_bit(n_pixels, n_actuators, density, seed):
    rng = np.random.default_rng(seed)
    F = sp.random(n_pixels, n_actuators, density=density, format="csr", random_state=rng)
    F.data = rng.standard_normal(F.nnz) * 10.0 ** rng.integers(-4, 4, F.nnz)  # magnitudes that round
    c = rng.standard_normal(n_actuators) * 300.0
    x = rng.standard_normal(n_pixels) * 1e3
    assert_same_as_scipy(F, c, x)


@pytest.mark.parametrize("influence", ["thin-plate", "gaussian"])
def test_the_mirrors_own_functions(influence):
    """The loop's matrix: the mirror's influence functions on an 80-px pupil."""
    pupil = Pupil(80)
    F = AsmGeometry(influence=influence).sparse_influence_functions(pupil)
    rng = np.random.default_rng(4)
    f = core_of(F)
    assert (f.n_pixels, f.n_actuators, f.nnz) == (F.shape[0], F.shape[1], F.nnz)
    assert_same_as_scipy(F, rng.standard_normal(F.shape[1]) * 200.0, rng.standard_normal(F.shape[0]) * 500.0)


def test_the_vectors_are_data():
    F = sp.csr_matrix(np.array([[1.0, 0.5], [0.0, 2.0], [0.25, 0.0]]))
    f = core_of(F)
    shape, seen = f.shape_and_adjoint(np.array([np.nan, 1.0]), np.array([1.0, np.inf, 0.0]))
    assert np.isnan(shape[0]) and shape[1] == 2.0 and np.isnan(shape[2])
    assert seen[0] == 1.0 and seen[1] == np.inf


def _csr(indptr=(0, 2, 3), indices=(0, 1, 1), values=(1.0, 0.5, 2.0)):
    return np.array(indptr), np.array(indices, dtype=np.int32), np.array(values)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"n_actuators": 0}, "n_actuators must be positive, got 0"),
        ({"indptr": (0,)}, r"indptr must hold n_pixels \+ 1 >= 2 row pointers"),
        ({"values": (1.0, 0.5)}, "indices and values must have the same length, got 3 and 2"),
        ({"indptr": (1, 2, 3)}, r"indptr must run from 0 to the number of entries \(3\), got 1..3"),
        ({"indptr": (0, 2, 4)}, r"indptr must run from 0 to the number of entries \(3\), got 0..4"),
        ({"indptr": (0, 3, 2, 3)}, "indptr must be non-decreasing, got 3 then 2 at row 1"),
        ({"indices": (0, 2, 1)}, "indices must be in 0..1, got 2 at entry 1"),
        ({"indices": (0, -1, 1)}, "indices must be in 0..1, got -1 at entry 1"),
        ({"values": (1.0, np.nan, 2.0)}, "values: values must be finite, got nan at index 1"),
        ({"values": (1.0, 0.5, -np.inf)}, "values: values must be finite, got -inf at index 2"),
    ],
)
def test_the_matrix_is_a_setting(change, message):
    indptr, indices, values = _csr(**{k: v for k, v in change.items() if k != "n_actuators"})
    with pytest.raises(ValueError, match=f"^{message}$"):
        InfluenceFunctions(indptr, indices, values, change.get("n_actuators", 2))


def test_wrong_dtypes_and_lengths_are_named():
    indptr, indices, values = _csr()
    with pytest.raises(ValueError, match="^values: expected dtype float64, got float32$"):
        InfluenceFunctions(indptr, indices, values.astype(np.float32), 2)
    with pytest.raises(ValueError, match=r"^indices: expected an integer array \(int32 or int64\), got float64$"):
        InfluenceFunctions(indptr, indices.astype(float), values, 2)
    with pytest.raises(ValueError, match="^indices: value 4294967296 at index 0 does not fit the index type$"):
        InfluenceFunctions(indptr, np.array([2**32, 1, 1]), values, 2)
    f = InfluenceFunctions(indptr, indices, values, 2)
    with pytest.raises(ValueError, match=r"^commands: expected shape \(2,\), got \(3,\)$"):
        f.shape(np.ones(3))
    with pytest.raises(ValueError, match="^opd: expected dtype float64, got float32$"):
        f.adjoint(np.ones(2, np.float32))
    with pytest.raises(ValueError, match=r"^opd: expected shape \(2,\), got \(2, 1\)$"):
        f.shape_and_adjoint(np.ones(2), np.ones((2, 1)))
    # a strided view is read as it is
    np.testing.assert_array_equal(f.shape(np.arange(4.0)[::2]), [1.0, 4.0])
