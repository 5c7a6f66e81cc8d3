"""The executors of ``--dask``: the local cluster's safety (loopback only, no dashboard,
processes, a memory limit, every process gone once closed), tasks and their errors, and the
one-line refusals of bad values and of a scheduler that does not answer."""

from __future__ import annotations

import os
import socket
import time
from pathlib import Path
from typing import Any

import helpers_dask
import pytest
from distributed.comm.utils import get_tcp_server_addresses
from helpers_cli import one_line_error, run

import lidarcal_ros
from lidarcal_ros.errors import ConfigError, InputError
from lidarcal_ros.pipeline.executor import (
    DaskExecutor,
    DaskTarget,
    SerialExecutor,
    deal_heaviest_first,
    local_worker_limit,
    open_executor,
    parse_dask_option,
    results_in_order,
    results_in_turn,
)

cluster = helpers_dask.cluster


def _refuse(value: int) -> int:
    raise InputError(f"value {value} refused")


def _pid() -> int:
    return os.getpid()


def test_a_local_cluster_listens_on_the_loopback_only_without_dashboard(
        cluster: DaskExecutor) -> None:
    info = cluster.client.scheduler_info(n_workers=-1)
    assert info["address"].startswith("tcp://127.0.0.1:")
    scheduler = cluster.cluster.scheduler
    # (Dask names its HTTP port "dashboard" whatever it serves: here nothing, on 127.0.0.1)
    assert {host for host, _port in get_tcp_server_addresses(scheduler.http_server)} == {
        "127.0.0.1"}
    assert not scheduler.http_application.wildcard_router.rules
    workers = info["workers"]
    assert len(workers) == 2 and cluster.workers == 2
    for address, worker in workers.items():
        assert address.startswith("tcp://127.0.0.1:")
        assert worker["nthreads"] == 1
        assert 0 < worker["memory_limit"] <= 4 * 2**30


def _environ(name: str) -> str | None:
    return os.environ.get(name)


def test_the_workers_have_one_malloc_arena_and_dasks_own_settings(
        cluster: DaskExecutor) -> None:
    """As the command line (cli/main.py): one glibc arena a process; Dask's own settings
    for its workers (e.g. MALLOC_TRIM_THRESHOLD_) kept."""
    assert cluster.submit(_environ, "MALLOC_ARENA_MAX", key="arenas").result() == "1"
    assert cluster.submit(_environ, "MALLOC_TRIM_THRESHOLD_", key="trim").result() == "65536"


def test_tasks_run_in_other_processes_and_their_errors_come_back(
        cluster: DaskExecutor) -> None:
    pids = {cluster.submit(_pid, key=f"pid-{i}").result() for i in range(4)}
    assert os.getpid() not in pids
    with pytest.raises(InputError, match="value 3 refused"):
        cluster.submit(_refuse, 3, key="refuse-3").result()


def _address() -> str:
    """The address of the worker running the task."""
    from distributed import get_worker

    return str(get_worker().address)


def test_a_task_runs_at_its_place_and_a_place_gone_is_no_error(
        cluster: DaskExecutor) -> None:
    places = cluster.places()
    assert len(places) == 2 and all(p.startswith("tcp://127.0.0.1:") for p in places)
    for i, place in enumerate(places * 3):
        assert cluster.submit(_address, key=f"at-{i}", place=place).result() == place
    # (a worker that died comes back at another address: its tasks run elsewhere)
    assert cluster.submit(_address, key="gone", place="tcp://127.0.0.1:9").result() in places
    with open_executor(None) as serial:
        assert serial.places() == []
        assert serial.submit(_pid, key="here", place=None).result() == os.getpid()


def test_items_are_dealt_heaviest_first_to_the_least_loaded_bin() -> None:
    # six strips, each the surface strip of 0 to 5 pairs: 5+2+1 and 4+3+0, not 6 and 9
    loads: list[tuple[int, ...]] = [(0,), (0,)]
    bins = deal_heaviest_first([(0,), (1,), (2,), (3,), (4,), (5,)], loads)
    assert bins == [1, 0, 0, 1, 1, 0] and loads == [(8,), (7,)]
    # ties on the first element broken by the next, then by the item's order; the loads
    # carried over from an earlier call
    loads = [(1, 0), (0, 0)]
    assert deal_heaviest_first([(1, 5), (1, 9), (1, 9)], loads) == [1, 1, 0]
    assert loads == [(2, 9), (2, 14)]


def _held_until(release: str) -> str:
    """Runs until the file ``release`` exists (two minutes at most)."""
    end = time.monotonic() + 120.0
    while not os.path.exists(release) and time.monotonic() < end:
        time.sleep(0.05)
    return "released"


def test_a_failed_task_raises_before_the_tasks_ahead_of_it_end(
        cluster: DaskExecutor, tmp_path: Path) -> None:
    release = tmp_path / "release"
    failing = cluster.submit(_refuse, 5, key="refuse-5")
    held: Any = cluster.submit(_held_until, str(release), key="held")
    try:
        with pytest.raises(InputError, match="value 5 refused"):
            results_in_order([held, failing])
        assert held.status == "pending"  # (raised while the task ahead still ran)
    finally:
        release.touch()
    assert held.result() == "released"
    assert results_in_order([held, cluster.submit(_pid, key="pid-after")])[0] == "released"
    with open_executor(None) as serial:
        done = [serial.submit(_pid, key="a"), serial.submit(_refuse, 6, key="b")]
        with pytest.raises(InputError, match="value 6 refused"):
            results_in_order(done)


def test_results_in_turn_come_in_order_and_a_failure_ahead_raises_at_once(
        cluster: DaskExecutor, tmp_path: Path) -> None:
    release = tmp_path / "release"
    first = cluster.submit(_pid, key="pid-first")
    failing = cluster.submit(_refuse, 7, key="refuse-7")
    held: Any = cluster.submit(_held_until, str(release), key="held-2")
    try:
        results = results_in_turn([first, held, failing])
        assert next(results) == first.result()
        with pytest.raises(InputError, match="value 7 refused"):
            next(results)
        assert held.status == "pending"  # (the failure behind it raised while it ran)
    finally:
        release.touch()
    assert list(results_in_turn([held, first])) == ["released", first.result()]


def test_closing_ends_every_process_of_the_local_cluster() -> None:
    executor = open_executor("local:1")
    assert isinstance(executor, DaskExecutor)
    pid = executor.submit(_pid, key="pid").result()
    nanny = executor.cluster
    executor.close()
    executor.close()  # (idempotent)
    assert nanny.status.name == "closed"
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)


def test_the_serial_executor_runs_at_once_and_keeps_errors() -> None:
    with open_executor(None) as executor:
        assert isinstance(executor, SerialExecutor)
        assert executor.submit(_pid, key="a").result() == os.getpid()
        failed = executor.submit(_refuse, 2, key="b")
        with pytest.raises(InputError, match="value 2 refused"):
            failed.result()


@pytest.mark.parametrize(("value", "target"), [
    ("local:2", DaskTarget(workers=2)),
    ("local:1", DaskTarget(workers=1)),
    ("tcp://10.0.0.5:8786", DaskTarget(address="tcp://10.0.0.5:8786")),
    ("tcp://scheduler.example.org:8786/", DaskTarget(address="tcp://scheduler.example.org:8786")),
])
def test_values_are_parsed(value: str, target: DaskTarget) -> None:
    assert parse_dask_option(value) == target


def test_plain_local_takes_one_process_per_core() -> None:
    assert parse_dask_option("local") == DaskTarget(workers=os.cpu_count() or 1)


@pytest.mark.parametrize(("value", "says"), [
    ("local:0", "N must be 1 to"),
    (f"local:{local_worker_limit() + 1}", "N must be 1 to"),
    ("local:two", "whole number"),
    ("local:-1", "whole number"),
    ("remote", "expected local, local:N or tcp://HOST:PORT"),
    ("tls://10.0.0.5:8786", "only a tcp:// scheduler"),
    ("tcp://10.0.0.5", "expected tcp://HOST:PORT"),
    ("tcp://10.0.0.5:99999", "expected tcp://HOST:PORT"),
    ("tcp://:8786", "expected tcp://HOST:PORT"),
    ("tcp://10.0.0.5:8786/path", "expected tcp://HOST:PORT"),
])
def test_bad_values_are_refused_in_one_line(value: str, says: str) -> None:
    with pytest.raises(ConfigError, match=f"--dask {value}: .*") as caught:
        parse_dask_option(value)
    assert says in str(caught.value) and "\n" not in str(caught.value)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_a_scheduler_that_does_not_answer_is_refused_within_the_timeout() -> None:
    address = f"tcp://127.0.0.1:{_free_port()}"
    with pytest.raises(ConfigError, match="no Dask scheduler answered within 1 s"):
        open_executor(address, timeout_s=1.0)


def test_the_command_refuses_a_bad_value_before_any_work(
        capsys: pytest.CaptureFixture[str], tmp_path: Any) -> None:
    cal = tmp_path / "cal.yaml"
    cal.write_text("lidarcal_calibration:\n  biases: {}\n")
    rc, _out, err = run(capsys, "correct", tmp_path / "missing", "--calibration", cal,
                        "-o", tmp_path / "out.laz", "--dask", "local:0")
    assert "--dask local:0: N must be 1 to" in one_line_error(rc, err, "correct")


def test_workers_of_another_version_are_refused(
        cluster: DaskExecutor, monkeypatch: pytest.MonkeyPatch) -> None:
    address = cluster.client.scheduler.address
    monkeypatch.setattr(lidarcal_ros, "__version__", "0.0.1")
    with pytest.raises(ConfigError, match=f"--dask {address}: workers run lidarcal_ros "
                       r"\d+\.\d+\.\d+, this is 0\.0\.1: install the same version"):
        open_executor(address)


@pytest.mark.filterwarnings("ignore:Port .* is already in use")
def test_a_scheduler_without_workers_is_refused() -> None:
    from distributed import LocalCluster

    with LocalCluster(n_workers=0, processes=False, protocol="tcp://", host="127.0.0.1",
                      dashboard_address=None) as empty:
        with pytest.raises(ConfigError, match="the scheduler has no worker"):
            open_executor(empty.scheduler_address, timeout_s=0.5)
