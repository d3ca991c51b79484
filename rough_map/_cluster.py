"""A Dask cluster to run on: one way to connect, for ``batch`` and ``survey``.

``scheduler`` is the address of a running ``dask scheduler`` (``tls://host:8786``, or
``tcp://`` on a trusted network); ``tls`` the PEM files of mutual TLS (CA, this client's
certificate and key), encryption then required. The workers must see the input files at
the same paths (a shared file system) and have rough_map installed.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from rough_map.errors import InputError

log = logging.getLogger(__name__)

__all__ = ["cluster_client"]


def cluster_client(scheduler: str, tls: tuple[str, str, str] | None = None) -> Any:
    """A :class:`distributed.Client` connected to ``scheduler``.

    Raises
    ------
    InputError
        dask.distributed is not installed, a TLS file is missing, the scheduler cannot be
        reached, or it needs TLS and none was given.
    """
    try:
        from distributed import Client, Security
    except ImportError:
        raise InputError(
            "--scheduler needs dask.distributed: pip install 'rough-map[cluster]'"
        ) from None
    security = None
    if tls is not None:
        for path in tls:
            if not Path(path).is_file():
                raise InputError(f"TLS file {path} does not exist")
        security = Security(
            tls_ca_file=tls[0], tls_client_cert=tls[1], tls_client_key=tls[2],
            require_encryption=True,
        )  # fmt: skip
    if security is None and not scheduler.startswith("tls://"):
        log.warning(
            "%s is not encrypted: keep the scheduler on a private network, or use tls://",
            scheduler,
        )
    try:
        return Client(scheduler, timeout="20s", security=security)
    except (OSError, TimeoutError) as exc:
        raise InputError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from None
    except TypeError as exc:  # a tls:// address without TLS files
        raise InputError(
            f"{scheduler} needs TLS: give --tls CA CERT KEY (or dask's "
            f"distributed.comm.tls configuration): {exc}"
        ) from None
