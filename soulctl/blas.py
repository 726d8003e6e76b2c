"""BLAS on one thread wherever a result must not depend on the machine.

Multi-threaded BLAS and LAPACK (OpenBLAS's eigh, pinv, matrix products) split their sums over
the threads they have, and floating-point sums depend on their order: the KL basis built with
1 and with 2 threads differed by 2e-6 (its interaction matrix and reconstructor by 1e-8 and
2e-6), and a closed loop amplifies the last bit (the R16.5 default run read 0.072 with one
thread and 0.078 with two).  The cached models (basis, calibrations, optical-gain and
variance tables) and the loop therefore run their BLAS on one thread: the same seed gives the
same numbers on every machine, whichever path (CLI, sweep, re-run) computed them.  The cost is
small: the loop's products are matrix-vector ones, and the basis builds in 2.0 s on one thread
against 2.6 s on two (80-pixel pupil).  scipy.fft's threads are not BLAS and keep the cores;
the pyramid's sums are ordered apart (``optics.pwfs.SUM_SHARES``).
"""

from __future__ import annotations

from threadpoolctl import threadpool_limits


def one_thread() -> threadpool_limits:
    """A context in which BLAS runs on one thread (``with blas.one_thread(): ...``)."""
    return threadpool_limits(limits=1, user_api="blas")
