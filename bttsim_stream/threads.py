"""One BLAS thread in every bttsim process.

The product's numerics are small dense solves and products (the modal model, the Eq. 16
fits), 30-100x slower with threaded BLAS on a small machine, and its outputs must not
depend on the machine: a threaded matrix product sums in another order, which moves the
last digit of a result (the same scenario and seed give bit-identical output only with the
same summation order everywhere). ``bttsim`` and every node program call
:func:`single_threaded_blas` first; the environment variables it sets reach the BLAS
libraries loaded later (scipy's own) and every child process (the nodes of ``bttsim run``).
"""

from __future__ import annotations

import os

__all__ = ["single_threaded_blas", "BLAS_THREAD_VARIABLES"]

#: The variables the BLAS and OpenMP runtimes read when they load.
BLAS_THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")


def single_threaded_blas() -> None:
    """Limit this process (and its children) to one BLAS / OpenMP thread: the variables for
    the libraries not loaded yet, :func:`threadpoolctl.threadpool_limits` for those loaded."""
    for name in BLAS_THREAD_VARIABLES:
        os.environ[name] = "1"
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1)
