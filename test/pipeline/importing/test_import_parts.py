"""``lidarcal import`` in parts (``--dask``): each tile read by a worker of a two-worker local
cluster, the bag written here byte for byte the serial import's, with an SBET and with the
trajectory rebuilt from multiple returns (the rays gathered by the workers), points spilled as
runs in both."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import helpers_dask
import pytest
from helpers_cli import one_line_error, run
from helpers_las import add_first_returns, plain_strips, write_las_tiles, write_mission_sbet

from lidarcal_ros.core.simulation.simulate import SimulatedMission, simulate_mission
from lidarcal_ros.core.simulation.spec import SimulationSpec
from lidarcal_ros.errors import InputError
from lidarcal_ros.pipeline.executor import DaskExecutor, Executor, SerialExecutor
from lidarcal_ros.pipeline.importing.importer import import_mission
from lidarcal_ros.pipeline.importing.options import ImportOptions, Returns

#: Runs of at most this many points: the serial and the parted import spill at other places.
MEMORY_POINTS = 20_000

cluster = helpers_dask.cluster


@pytest.fixture(scope="module")
def sim() -> SimulatedMission:
    return simulate_mission(SimulationSpec.from_options(
        density=0.1, line_length_m=250.0, seed=11, origin=(500_000.0, 5_000_000.0)))


def _tiles(folder: Path) -> Path:
    folder.mkdir()
    return folder


def _imported(tiles: list[Path], folder: Path, options: ImportOptions,
              executor: Executor | None = None) -> bytes:
    folder.mkdir()
    out = folder / "mission.mcap"
    import_mission(tiles, out, options, executor=executor)
    assert [p.name for p in folder.iterdir()] == ["mission.mcap"], "parts left behind"
    return out.read_bytes()


def test_tiles_read_by_two_workers_make_the_serial_bag(
        sim: SimulatedMission, cluster: DaskExecutor, tmp_path: Path) -> None:
    tiles = write_las_tiles(plain_strips(sim), _tiles(tmp_path / "tiles"), laz=(1, 2))
    sbet = write_mission_sbet(sim.mission, tmp_path / "tiles" / "mission.out")
    options = ImportOptions(trajectory=sbet, memory_points=MEMORY_POINTS)
    serial = _imported(tiles, tmp_path / "serial", options)
    assert _imported(tiles, tmp_path / "dask", options, cluster) == serial


def test_the_trajectory_rebuilt_from_the_workers_rays_is_the_serial_one(
        sim: SimulatedMission, cluster: DaskExecutor, tmp_path: Path) -> None:
    tiles = write_las_tiles(add_first_returns(sim, fraction=0.3, seed=4),
                            _tiles(tmp_path / "tiles"), laz=(0,))
    options = ImportOptions(trajectory="estimate", returns=Returns.LAST,
                            memory_points=MEMORY_POINTS)
    serial = _imported(tiles, tmp_path / "serial", options)
    assert _imported(tiles, tmp_path / "dask", options, cluster) == serial
    assert _imported(tiles, tmp_path / "here", options, SerialExecutor()) == serial


def test_a_bad_file_read_by_a_worker_is_one_error_and_leaves_nothing(
        sim: SimulatedMission, cluster: DaskExecutor, tmp_path: Path) -> None:
    tiles = write_las_tiles(plain_strips(sim), _tiles(tmp_path / "tiles"), laz=())
    sbet = write_mission_sbet(sim.mission, tmp_path / "tiles" / "mission.out")
    data = bytearray(tiles[-1].read_bytes())
    tiles[-1].write_bytes(bytes(data[: len(data) // 2]))  # (a truncated tile)
    out = tmp_path / "out"
    out.mkdir()
    options: Any = ImportOptions(trajectory=sbet, memory_points=MEMORY_POINTS)
    with pytest.raises(InputError):
        import_mission(tiles, out / "mission.mcap", options, executor=cluster)
    assert list(out.iterdir()) == []


def test_the_command_refuses_a_bad_value_before_reading(
        capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    rc, _out, err = run(capsys, "import", tmp_path / "missing.las", "-o",
                        tmp_path / "out.mcap", "--dask", "tcp://nowhere")
    assert "--dask tcp://nowhere: expected tcp://HOST:PORT" in one_line_error(rc, err, "import")
