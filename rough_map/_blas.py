"""BLAS on one thread, for the small matrices multiplied per frame.

OpenBLAS splits even a (N, 3) @ (3, 3) product over its threads, which costs more than the
product on a busy machine, and splits sums in an order that depends on its thread count
(so results would differ in their last bits between processes). threadpoolctl limits it,
but finding the loaded BLAS libraries reads each of the process's shared libraries: 3 ms,
more than a chunk of frames' products. :func:`one_blas_thread` finds them once, and again
only after new modules were imported (which may have loaded another BLAS).
"""

from __future__ import annotations

import sys
from contextlib import AbstractContextManager
from typing import Any

__all__ = ["one_blas_thread"]

_found: tuple[int, Any] | None = None  # (modules imported when found, the controller)


def one_blas_thread() -> AbstractContextManager[Any]:
    """A context manager within which BLAS uses one thread (then as before)."""
    global _found
    from threadpoolctl import ThreadpoolController

    if _found is None or _found[0] != len(sys.modules):
        _found = (len(sys.modules), ThreadpoolController())
    return _found[1].limit(limits=1, user_api="blas")
