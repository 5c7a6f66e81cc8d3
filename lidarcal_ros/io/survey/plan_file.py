"""Flight plans (docs/interface.md "Flight plan") from YAML, with the DSM they name read in."""

from __future__ import annotations

import os
from pathlib import Path

from lidarcal_ros.core.planning import FlightPlan
from lidarcal_ros.io.survey.dsm import read_dsm
from lidarcal_ros.io.yaml_file import read_yaml


def read_flight_plan(path: str | os.PathLike[str]) -> FlightPlan:
    """Read and validate a flight plan; a DSM ``terrain`` path (relative to the plan's
    directory) is read with :func:`~lidarcal_ros.io.survey.dsm.read_dsm`.

    Raises
    ------
    ConfigError, InputError
        One line naming the file and key at fault.
    """
    p = Path(path)
    plan = FlightPlan.from_mapping(read_yaml(p, what="flight plan"), source=str(p))
    if plan.uses_dsm:
        dsm_path = Path(plan.terrain).expanduser()
        if not dsm_path.is_absolute():
            dsm_path = p.parent / dsm_path
        plan.dsm = read_dsm(dsm_path, cell_m=plan.terrain_cell_m,
                            north_west=plan.terrain_origin, centre=plan.centre())
    return plan


__all__ = ["read_flight_plan"]
