"""Property-based fuzzing of the YAML readers: any text as a YAML file, flight configuration
or calibration is read or refused with a one-line LidarcalError, never another exception."""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from helpers_fuzz import BUDGET, mutated_text
from hypothesis import example, given
from hypothesis import strategies as st

from lidarcal_ros.core.params import PARAMETER_NAMES
from lidarcal_ros.errors import LidarcalError
from lidarcal_ros.io.calibration_file import ROOT_KEY, read_calibration
from lidarcal_ros.io.config_file import load_flight_config
from lidarcal_ros.io.yaml_file import read_yaml

ROOT = Path(__file__).parents[2]
CONFIG = (ROOT / "config" / "flight_config.yaml").read_text()
CALIBRATION = f"{ROOT_KEY}:\n  biases:\n" + "".join(
    f"    {name}:\n      value: 0.001\n      sigma: 0.0001\n      estimated: true\n"
    for name in PARAMETER_NAMES)
_DIR = tempfile.TemporaryDirectory(prefix="lidarcal-fuzz-")


def _check(read: Callable[[Path], Any], text: str) -> None:
    path = Path(_DIR.name) / "fuzz.yaml"
    path.write_bytes(text.encode("utf-8", errors="surrogatepass"))
    try:
        read(path)
    except LidarcalError as err:
        assert "\n" not in str(err)


@BUDGET
@given(st.text(alphabet=st.sampled_from([*list("[]{}:-&*!|>'\"#,?\n\t ab01.e~%"), "\x00"]),
               max_size=200))
@example("a: &x [*x]")
def test_any_text_is_read_or_refused_as_yaml(text: str) -> None:
    _check(read_yaml, text)


@BUDGET
@given(mutated_text(CONFIG))
def test_a_damaged_flight_configuration_is_read_or_refused(text: str) -> None:
    _check(load_flight_config, text)


@BUDGET
@given(mutated_text(CALIBRATION))
def test_a_damaged_calibration_is_read_or_refused(text: str) -> None:
    _check(read_calibration, text)


def test_the_seeds_are_read() -> None:
    """The mutations start from files the readers take."""
    path = Path(_DIR.name) / "seed.yaml"
    path.write_text(CALIBRATION)
    assert read_calibration(path).values["dX"] == 0.001
    path.write_text(CONFIG)
    load_flight_config(path)
