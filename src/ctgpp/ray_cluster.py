"""Ray, optional (``pip install "ctgpp[ray]"``), for ``generate`` and ``evaluate`` with ``--engine ray``:
imported only when asked for, with a one-line error when missing, and a session on a cluster joined
at an address or started on this machine."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from typing import Any

MAX_RETRIES = 3  # a Ray task whose worker died runs again, at most this often


class MissingRayError(ImportError, ValueError):
    """``--engine ray`` without Ray installed (a one-line user error in the CLI)."""


def import_ray() -> Any:
    """The ``ray`` module, or :class:`MissingRayError` saying how to install it."""
    try:
        import ray
    except ImportError:
        raise MissingRayError('--engine ray needs Ray: pip install "ctgpp[ray]"') from None
    return ray


@contextlib.contextmanager
def ray_session(ray: Any, workers: int, address: str | None) -> Iterator[None]:
    """Ray connected for the block: to the cluster at ``address`` (e.g. ``10.0.0.5:6379`` or
    ``auto``), else to a Ray instance started here with ``workers`` CPUs; the connection made here is
    closed at the end (a session already open is left as it is)."""
    if ray.is_initialized():
        yield
        return
    if address:
        ray.init(address=address, log_to_driver=False, logging_level=logging.WARNING)
    else:
        ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False,
                 logging_level=logging.WARNING)
    try:
        yield
    finally:
        ray.shutdown()
