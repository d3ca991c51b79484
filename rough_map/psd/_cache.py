"""Tables a process computes once, the same bits in every process.

The estimator's tables (windows, projections, leakage, the standard-error kernels) are
computed once per geometry and cached. Several are built with matrix products, and OpenBLAS
splits a product's sums by its number of threads: a table built on two threads differs in the
last bit from one built on one. A worker (BLAS pinned to one thread) and a main process that
built its tables earlier on two would then read the same patch differently. So the tables are
built with BLAS on one thread, whatever the caller's setting.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import lru_cache, wraps
from typing import Any, TypeVar

from rough_map._blas import one_blas_thread

F = TypeVar("F", bound=Callable[..., Any])


def table_cache(maxsize: int) -> Callable[[F], F]:
    """:func:`functools.lru_cache` of a function computed with BLAS on one thread."""

    def decorate(fn: F) -> F:
        @wraps(fn)
        def one_thread(*args: Any, **kwargs: Any) -> Any:
            with one_blas_thread():
                return fn(*args, **kwargs)

        return lru_cache(maxsize=maxsize)(one_thread)  # type: ignore[return-value]

    return decorate
