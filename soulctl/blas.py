"""BLAS on one thread wherever a result must not depend on the machine.

Multi-threaded BLAS and LAPACK (OpenBLAS's eigh, pinv, matrix products) split their sums over
the threads they have, and floating-point sums depend on their order: the KL basis built with
1 and with 2 threads differed by 2e-6 (its interaction matrix and reconstructor by 1e-8 and
2e-6), and a closed loop amplifies the last bit (the R16.5 default run read 0.072 with one
thread and 0.078 with two).  The functions that build a model (``on_one_thread``: the basis,
the calibrations, the optical-gain and variance tables, the sky-like calibration error, modes
derived from a telemetry file, the Tip/Tilt filter design) and the loop therefore run their
BLAS on one thread: the same seed gives the same numbers on every machine, whichever path
(CLI, sweep, re-run) computed them.  The cost is small: the loop's products are matrix-vector
ones, and the basis builds in 2.0 s on one thread against 2.6 s on two (80-pixel pupil); the
design, whose products are short sums, ran as fast on one thread with half the CPU time.
scipy.fft's threads are not BLAS and keep the cores; the pyramid's sums are ordered apart (``optics.pwfs.SUM_SHARES``).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import ParamSpec, TypeVar

from threadpoolctl import threadpool_limits

P = ParamSpec("P")
T = TypeVar("T")


def one_thread() -> threadpool_limits:
    """A context in which BLAS runs on one thread (``with blas.one_thread(): ...``)."""
    return threadpool_limits(limits=1, user_api="blas")


def on_one_thread(function: Callable[P, T]) -> Callable[P, T]:
    """``function`` with BLAS on one thread during each call: for the functions that build a
    model, so that every caller gets the same numbers."""

    @functools.wraps(function)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> T:
        with one_thread():
            return function(*args, **kwargs)

    return wrapper
