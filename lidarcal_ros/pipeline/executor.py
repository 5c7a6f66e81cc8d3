"""Where the heavy commands run their parts: here, one after another, or on a Dask cluster.

``--dask local[:N]`` starts N worker processes on this machine (127.0.0.1 only, no dashboard),
``--dask tcp://HOST:PORT`` uses an existing scheduler; :func:`open_executor` gives an
:class:`Executor` for either (or for none: :class:`SerialExecutor`), shut down on every way
out of its ``with`` block.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import os
import re
import uuid
import warnings
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar, cast
from urllib.parse import urlsplit

from lidarcal_ros.errors import ConfigError

__all__ = [
    "CONNECT_TIMEOUT_S", "LOCAL_WORKER_MEMORY_BYTES", "CommandTasks", "DaskExecutor",
    "DaskTarget", "Executor", "SerialExecutor", "TaskFuture", "deal_heaviest_first",
    "local_worker_limit",
    "open_executor", "parse_dask_option", "results_in_order", "results_in_turn",
]

logger = logging.getLogger(__name__)

T = TypeVar("T")
T_co = TypeVar("T_co", covariant=True)

#: Seconds to wait for a scheduler (and for its first worker) before giving up.
CONNECT_TIMEOUT_S = 10.0
#: Memory limit of each local worker process (bytes): a part's correction holds well under
#: 1 GB, and Dask restarts a worker that passes 95 % of its limit rather than let the machine
#: swap. Lowered where N workers would take more than half of the machine's memory.
LOCAL_WORKER_MEMORY_BYTES = 4 * 2**30


class TaskFuture(Protocol[T_co]):
    """What :meth:`Executor.submit` returns: its result, waited for (a task's exception
    raised again)."""

    def result(self, timeout: float | None = None) -> T_co:
        """The task's value (its exception raised here)."""
        ...

    def done(self) -> bool:
        """The task has ended (run, failed or cancelled)."""
        ...


class Executor(Protocol):
    """Runs the parts of a command: :meth:`submit` each, then take each future's result."""

    #: Parts that run at the same time (1: one after another).
    workers: int
    #: Words for the summary, e.g. ``"Dask local cluster, 2 worker processes"``.
    description: str

    def submit(self, fn: Callable[..., T], *args: Any, key: str,
               place: str | None = None) -> TaskFuture[T]:
        """Run ``fn(*args)`` (``key``: a name unique among the command's tasks), on the
        worker ``place`` (one of :meth:`places`) while it is there."""
        ...

    def places(self) -> list[str]:
        """The workers a task can be placed on (none: one place, this process)."""
        ...

    def close(self) -> None:
        """Stop what :func:`open_executor` started (idempotent)."""
        ...


class SerialExecutor:
    """Every part in this process, one after another, at :meth:`submit`."""

    workers = 1
    description = "serial (this process)"

    def submit(self, fn: Callable[..., T], *args: Any, key: str,
               place: str | None = None) -> TaskFuture[T]:
        """Run ``fn(*args)`` now (an argument that is a future of this executor's: its
        result, as Dask passes a task the results of those it takes); a finished future
        (its exception kept for ``result``)."""
        future: Future[T] = Future()
        try:
            future.set_result(fn(*(a.result() if isinstance(a, Future) else a for a in args)))
        except Exception as exc:  # raised again by result(), as Dask's futures do
            future.set_exception(exc)
        return future

    def places(self) -> list[str]:
        """None: every task runs here."""
        return []

    def close(self) -> None:
        """Nothing to stop."""

    def __enter__(self) -> SerialExecutor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def results_in_turn(futures: Sequence[TaskFuture[T]]) -> Iterator[T]:
    """Each future's value, in order, each as soon as it and those before it are done. A
    task that fails for good (its exception, or Dask's ``KilledWorker`` once its workers died
    too often) raises here as soon as it has failed, not after every task before it has
    ended: a cluster short of memory ends the command instead of restarting its workers for
    as long as the others take."""
    remote = [f for f in futures if not isinstance(f, Future)]
    finished: Iterator[Any] = iter(())
    if remote:
        from distributed import as_completed

        finished = iter(as_completed(remote))
    for future in futures:
        while not isinstance(future, Future) and not cast(Any, future).done():
            other = next(finished, None)
            if other is None:
                break
            if other.status == "error":
                other.result()  # (raises the task's exception)
        yield future.result()


def results_in_order(futures: Sequence[TaskFuture[T]]) -> list[T]:
    """Each future's value, in order (:func:`results_in_turn`: a failure raises at once)."""
    return list(results_in_turn(futures))


def deal_heaviest_first(weights: Sequence[tuple[int, ...]],
                        loads: list[tuple[int, ...]]) -> list[int]:
    """Items dealt to bins, the heaviest first (then in their order), each to the bin of
    least load so far (then the first): the bin of each item, in the items' order.
    ``loads`` (one per bin, tuples as long as the weights, compared in order) are updated:
    each bin's load is the sum of its items' weights, element by element."""
    bins = [0] * len(weights)
    for i in sorted(range(len(weights)), key=lambda i: (tuple(-w for w in weights[i]), i)):
        b = min(range(len(loads)), key=lambda b: (loads[b], b))
        loads[b] = tuple(load + w for load, w in zip(loads[b], weights[i], strict=True))
        bins[i] = b
    return bins


def _value(value: T) -> T:
    """``value`` itself (a task: what :meth:`CommandTasks.send` sends)."""
    return value


class CommandTasks:
    """One command's tasks on ``executor``: each key made unique (a scheduler shared by
    several commands keeps a finished key's result), a value the tasks share sent once.

    Values go to the workers inside their tasks, which the scheduler keeps: a task whose
    worker died runs again elsewhere from them, and no shared file system is needed.
    """

    def __init__(self, executor: Executor, command: str) -> None:
        self.executor = executor
        self.workers, self.description = executor.workers, executor.description
        self._prefix = f"{command}-{uuid.uuid4().hex[:8]}"
        self._numbers = itertools.count()
        #: By id, the value sent and its future (the value held: its id stays its own).
        self._sent: dict[int, tuple[object, TaskFuture[Any]]] = {}

    def submit(self, fn: Callable[..., T], *args: Any, key: str,
               place: str | None = None) -> TaskFuture[T]:
        """``fn(*args)`` on the executor (``key``: the task's name, made unique here; ``place``:
        :meth:`Executor.submit`'s)."""
        with warnings.catch_warnings():
            # (data in its task is what keeps the work resilient: no other copy to load)
            warnings.filterwarnings("ignore", message=".*[Ll]arge (graph|object)")
            return self.executor.submit(
                fn, *args, key=f"{self._prefix}-{key}-{next(self._numbers)}", place=place)

    def send(self, value: T, name: str) -> TaskFuture[T]:
        """``value`` on the workers, to pass to tasks in its place (sent once however often
        it is asked for)."""
        sent = self._sent.get(id(value))
        if sent is None or sent[0] is not value:
            sent = (value, self.submit(_value, value, key=name))
            self._sent[id(value)] = sent
        return sent[1]

    def close(self) -> None:
        """Nothing to stop (the executor's owner closes it)."""


@dataclass(frozen=True)
class DaskTarget:
    """A parsed ``--dask`` value: a local cluster of ``workers`` processes (``address``
    None) or the scheduler at ``address`` (``tcp://HOST:PORT``)."""

    workers: int | None = None
    address: str | None = None


def local_worker_limit() -> int:
    """The most worker processes ``--dask local:N`` starts: twice the cores (more only
    contend for them)."""
    return max(2, 2 * (os.cpu_count() or 1))


def parse_dask_option(value: str) -> DaskTarget:
    """``local``, ``local:N`` or ``tcp://HOST:PORT`` as a :class:`DaskTarget`.

    Raises
    ------
    ConfigError
        One line naming what is wrong with ``value``.
    """
    text = value.strip()
    limit = local_worker_limit()
    if text == "local":
        return DaskTarget(workers=min(os.cpu_count() or 1, limit))
    if text.startswith("local:"):
        n = text[len("local:"):]
        if not re.fullmatch(r"[0-9]+", n):
            raise ConfigError(f"--dask {value}: N of local:N must be a whole number of "
                              "worker processes")
        if not 1 <= int(n) <= limit:
            raise ConfigError(f"--dask {value}: N must be 1 to {limit} worker processes "
                              f"(twice this machine's {os.cpu_count()} cores)")
        return DaskTarget(workers=int(n))
    if "://" not in text:
        raise ConfigError(f"--dask {value}: expected local, local:N or tcp://HOST:PORT")
    parts = urlsplit(text)
    if parts.scheme != "tcp":
        raise ConfigError(f"--dask {value}: only a tcp:// scheduler address is supported, "
                          f"not {parts.scheme}://")
    try:
        port = parts.port
    except ValueError:
        port = None
    if not parts.hostname or port is None or not 0 < port < 65536 or \
            parts.path not in ("", "/") or parts.query or parts.username:
        raise ConfigError(f"--dask {value}: expected tcp://HOST:PORT (a port 1-65535)")
    return DaskTarget(address=f"tcp://{parts.netloc}")


class DaskExecutor:
    """Parts submitted to a Dask cluster (:func:`open_executor`); :meth:`close` stops the
    client and any local cluster this started."""

    def __init__(self, client: Any, cluster: Any, description: str) -> None:
        self.client, self.cluster, self.description = client, cluster, description
        self.workers = max(len(client.scheduler_info(n_workers=-1)["workers"]), 1)

    def submit(self, fn: Callable[..., T], *args: Any, key: str,
               place: str | None = None) -> TaskFuture[T]:
        """``fn(*args)`` on a worker, ``place`` while it lives (retried on another if its
        worker dies: parts are written atomically and written again whole)."""
        # (pure=False: a part is run again when asked again, never served from a cache;
        # a place is loose: a worker that died comes back at another address)
        where: dict[str, Any] = {} if place is None else {"workers": [place],
                                                          "allow_other_workers": True}
        future: TaskFuture[T] = self.client.submit(fn, *args, key=key, pure=False, **where)
        return future

    def places(self) -> list[str]:
        """The workers' addresses, as the scheduler knows them now."""
        return sorted(self.client.scheduler_info(n_workers=-1)["workers"])

    def close(self) -> None:
        """Close the client, then stop the local cluster (its processes) if this made one."""
        client, cluster, self.client, self.cluster = self.client, self.cluster, None, None
        if client is None and cluster is None:
            return
        # What Dask says while its processes end (heartbeats unanswered, exit codes already
        # read after a Ctrl-C reached them too) is no news about the command's work.
        logging.getLogger("distributed").setLevel(logging.CRITICAL)
        try:
            if client is not None:
                client.close()
        finally:
            if cluster is not None:
                cluster.close()

    def __enter__(self) -> DaskExecutor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _local_memory_limit(workers: int) -> int:
    """Each local worker's memory limit (bytes): :data:`LOCAL_WORKER_MEMORY_BYTES`, at most
    half of the machine's memory shared among the workers."""
    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    return int(min(LOCAL_WORKER_MEMORY_BYTES, total // (2 * workers)))


def _quiet_dask() -> None:
    """Dask's own news (cluster started, scheduler address) stay out of the command's
    output; its warnings and errors still show."""
    for name in ("distributed", "dask"):
        logging.getLogger(name).setLevel(logging.WARNING)


def _abandon(cluster: Any) -> None:
    """Stop what there is of a local cluster whose start was interrupted, and keep Dask's
    exit handler from trying again (it fails, with a traceback, on workers not yet started);
    its worker processes are daemons: they end with this process whatever happens here."""
    cluster.shutdown_on_close = False
    for name in ("distributed", "asyncio"):  # (its start's tasks, failed, as the loop ends)
        logging.getLogger(name).setLevel(logging.CRITICAL)
    with contextlib.suppress(Exception):
        cluster.close(timeout=5)


def _start_local(workers: int, timeout_s: float) -> DaskExecutor:
    import dask
    from distributed import Client, LocalCluster
    from distributed.deploy.spec import SpecCluster

    _quiet_dask()

    # Processes (the correction's Python holds the interpreter lock), one thread each,
    # listening on the loopback only, no dashboard (and no page at all on the HTTP port a
    # scheduler and its workers open anyway, there too); the nannies restart a dead worker.
    # Each worker one malloc arena, as the command line has (cli/main.py).
    environ = {**dask.config.get("distributed.nanny.pre-spawn-environ", {}),
               "MALLOC_ARENA_MAX": 1}
    with dask.config.set({"distributed.worker.daemon": True,
                          "distributed.nanny.pre-spawn-environ": environ,
                          "distributed.scheduler.http.routes": [],
                          "distributed.worker.http.routes": [],
                          "distributed.comm.timeouts.connect": f"{timeout_s}s"}), \
            warnings.catch_warnings():
        # (that port is the HTTP server's, serving nothing: another one is as good)
        warnings.filterwarnings("ignore", message="Port .* is already in use")
        started = set(SpecCluster._instances)
        try:
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                   host="127.0.0.1", dashboard_address=None,
                                   memory_limit=_local_memory_limit(workers),
                                   silence_logs=logging.CRITICAL)
        except BaseException:  # (Ctrl-C, SIGTERM while it starts: no object to close)
            for half_built in set(SpecCluster._instances) - started:
                _abandon(half_built)
            raise
        try:
            client = Client(cluster, timeout=timeout_s)
        except BaseException:
            cluster.close()
            raise
    return DaskExecutor(client, cluster, f"Dask local cluster, {workers} worker processes")


def _connect(address: str, timeout_s: float) -> DaskExecutor:
    from distributed import Client

    _quiet_dask()
    try:
        client = Client(address, timeout=timeout_s)
    except (OSError, TimeoutError) as exc:
        raise ConfigError(f"--dask {address}: no Dask scheduler answered within "
                          f"{timeout_s:g} s ({type(exc).__name__})") from None
    executor = DaskExecutor(client, None, "")
    try:
        _check_workers(executor, address, timeout_s)
    except BaseException:
        executor.close()
        raise
    return executor


def _lidarcal_version() -> str:
    """The version of lidarcal_ros where the function runs (a worker)."""
    from lidarcal_ros import __version__

    return __version__


def _check_workers(executor: DaskExecutor, address: str, timeout_s: float) -> None:
    """Refuse a cluster without workers, or whose workers run another lidarcal_ros."""
    from lidarcal_ros import __version__

    client = executor.client
    try:
        client.wait_for_workers(1, timeout=timeout_s)
    except TimeoutError:
        raise ConfigError(f"--dask {address}: the scheduler has no worker (none joined "
                          f"within {timeout_s:g} s)") from None
    try:
        versions = client.run(_lidarcal_version)
    except ImportError:
        raise ConfigError(f"--dask {address}: a worker cannot import lidarcal_ros; install "
                          "this package and requirements.txt on every worker") from None
    other = sorted({v for v in versions.values() if v != __version__})
    if other:
        raise ConfigError(f"--dask {address}: workers run lidarcal_ros {', '.join(other)}, "
                          f"this is {__version__}: install the same version everywhere")
    executor.workers = len(versions)
    executor.description = f"Dask scheduler {address}, {len(versions)} workers"


def open_executor(value: str | None, *, timeout_s: float = CONNECT_TIMEOUT_S
                  ) -> SerialExecutor | DaskExecutor:
    """The executor ``--dask value`` asks for (None: :class:`SerialExecutor`); use it in a
    ``with`` block, which shuts a local cluster down on every way out (errors, Ctrl-C,
    SIGTERM: :mod:`lidarcal_ros.cli.exit_status` turns it into an exception).

    Raises
    ------
    ConfigError
        A malformed value, or no scheduler answering within ``timeout_s`` seconds.
    """
    if value is None:
        return SerialExecutor()
    target = parse_dask_option(value)
    if target.address is not None:
        return _connect(target.address, timeout_s)
    assert target.workers is not None
    return _start_local(target.workers, timeout_s)
