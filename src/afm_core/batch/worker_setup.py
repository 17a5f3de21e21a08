"""Dask worker preload of the embedded cluster (`runner.dask_client`): its workers ignore SIGINT.

Why: Ctrl-C in a terminal signals the whole process group, so every worker process raised its
own KeyboardInterrupt mid-task and printed two tracebacks, while the `afm batch` process was
already closing the cluster, which stops them anyway, and keeps the rows written. Dask runs a
preload's dask_setup in the worker's event loop, on the process's main thread, the only thread
that may set a signal's handler; it runs again in every worker the nanny restarts.
"""

import signal


def dask_setup(worker) -> None:  # noqa: ARG001 - Dask's preload signature
    signal.signal(signal.SIGINT, signal.SIG_IGN)
