"""The Dask cluster a tiled fit runs on (:func:`open_client`): a local cluster on this machine
by default, or an existing one by its scheduler's address.

The local cluster is Dask's embedded one (nothing to start): one worker process per core
(``workers``, default :func:`os.cpu_count`), one thread per worker, its dashboard on a
free port. Each tile
then runs Dr.Jit's LLVM backend on as many threads as its worker has, at least two (a pool
of one thread hangs), so that N workers use about N cores instead of N x N threads.

An existing cluster (``scheduler = "tcp://HOST:PORT"``) is started on the machines with
``dask scheduler`` and ``dask worker tcp://HOST:PORT --nworkers N --nthreads 1``
(docs/rti.md, "Tiles and clusters"); its workers need this package and the capture's images
at the same path as the machine that submits the fit.
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Iterator
from contextlib import contextmanager

from .._checks import check_range
from .checks import check_count

__all__ = ["SCHEDULER_TIMEOUT", "check_scheduler", "check_workers", "open_client",
           "worker_threads"]

#: Seconds to wait for a scheduler to answer
SCHEDULER_TIMEOUT = 10.0
#: ``tcp://HOST:PORT`` (or ``tls://``): a host name, an IPv4 address or an [IPv6] address
_ADDRESS = re.compile(r"^(tcp|tls)://(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9]([A-Za-z0-9.-]*[A-Za-z0-9])?)"
                      r":(\d{1,5})$")


def check_workers(value, name: str = "workers") -> int:
    """A number of local worker processes: a whole number >= 1."""
    if isinstance(value, bool):
        raise ValueError(f"{name} = {value!r} is not a whole number; valid range is [1, inf]")
    return check_count(name, value, 1)


def check_scheduler(address, name: str = "scheduler") -> str:
    """A scheduler address ``tcp://HOST:PORT`` (or ``tls://``), port 1-65535."""
    text = str(address).strip() if isinstance(address, str) else None
    match = _ADDRESS.match(text) if text else None
    if match is None or not 1 <= int(match.group(4)) <= 65535:
        raise ValueError(f"{name} = {address!r} is not a Dask scheduler address; expected "
                         "tcp://HOST:PORT with a port in 1-65535 (e.g. tcp://10.0.0.5:8786, "
                         "as printed by `dask scheduler`)")
    return text


@contextmanager
def open_client(client=None, scheduler: str | None = None, workers: int | None = None,
                timeout: float = SCHEDULER_TIMEOUT, names: tuple[str, str] = ("scheduler",
                                                                                "workers")
                ) -> Iterator:
    """A :class:`distributed.Client` for the block: ``client`` itself (left open), one
    connected to ``scheduler``, or one of a new local cluster of ``workers`` processes (both
    closed after the block).

    Args:
        client: an existing :class:`distributed.Client`, or None.
        scheduler: an existing cluster's scheduler, ``tcp://HOST:PORT``.
        workers: local worker processes (one thread each), >= 1; default one per core. Only
            for the local cluster.
        timeout: seconds to wait for ``scheduler`` to answer, > 0.
        names: the names of ``scheduler`` and ``workers`` in messages (e.g. the options).

    Raises:
        ValueError: a bad ``scheduler`` or ``workers``, both given, or no scheduler answering
            within ``timeout``.
    """
    from distributed import Client, LocalCluster

    if client is not None:
        yield client
        return
    if scheduler is not None:
        address = check_scheduler(scheduler, names[0])
        if workers is not None:
            raise ValueError(f"{names[1]} = {workers!r} applies to the local cluster only; "
                             f"with {names[0]} the cluster's own workers are used")
        timeout = check_range("timeout", timeout, 0.0, 3600.0, "(]")
        try:
            remote = Client(address, timeout=timeout)
        except (OSError, TimeoutError) as exc:
            raise ValueError(f"{names[0]} = {address!r}: no Dask scheduler answered within "
                             f"{timeout:g} s ({exc}); start one with `dask scheduler` and "
                             "give the address it prints") from None
        with remote:
            yield remote
        return
    n = check_workers((os.cpu_count() or 1) if workers is None else workers, names[1])
    # the dashboard on a free port: a second cluster on this machine must not fail or warn
    with LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                      dashboard_address=":0", silence_logs=logging.ERROR) as cluster, \
            Client(cluster) as local:
        yield local


def worker_threads() -> int | None:
    """Threads of the Dask worker running the calling task (None outside a worker)."""
    try:
        from distributed import get_worker

        return int(get_worker().state.nthreads)
    except (ImportError, ValueError, AttributeError):
        return None
