"""BLAS thread control for loops of many tiny linear-algebra calls."""

from __future__ import annotations

from contextlib import AbstractContextManager, nullcontext

__all__ = ["single_threaded_blas"]


def single_threaded_blas() -> AbstractContextManager:
    """Limit BLAS to one thread (a context manager; a no-op without ``threadpoolctl``).

    Fold-ins, kriging solves and planner criteria work on tiny matrices (k = 5, a few hundred
    cells) where OpenBLAS's thread pool only adds synchronisation: on a loaded 2-core machine
    the kriging solves ran ~10x slower with the default threads (5.2 s vs 0.56 s for one start
    cell of the demo). threadpoolctl limits only the libraries loaded when it is called, so
    scipy's own OpenBLAS (used by ``scipy.linalg``) is loaded first.
    """
    import scipy.linalg  # noqa: F401  (loads scipy's BLAS so that the limit reaches it)

    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - a core dependency; kept for odd installs
        return nullcontext()
    return threadpool_limits(limits=1, user_api="blas")
