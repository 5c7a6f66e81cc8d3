"""Property-based fuzzing of the MCAP and CDR reading path: a small valid bag, damaged
anyhow, is read or refused with a BagError (one line), never another exception or a hang."""

from __future__ import annotations

import tempfile
from pathlib import Path

import helpers_mcap as mc
from helpers_fuzz import BUDGET, mutated_bytes
from hypothesis import event, given

from lidarcal_ros.errors import BagError
from lidarcal_ros.io.bag.reader import BagReader, ReadableMcap

_SEEDS = {"zstd": mc.valid_mcap(4, "zstd"), "lz4": mc.valid_mcap(4, "lz4"),
          "unindexed": mc.mcap_file([mc.chunk_of(b"".join(
              mc.message_record(1_000_000_000 + k, mc.string_message(f"m{k}"))
              for k in range(3)))], summary=False)}
# One directory for every example: hypothesis runs examples in a loop, not as pytest tests.
_DIR = tempfile.TemporaryDirectory(prefix="lidarcal-fuzz-")


def _read(data: bytes) -> None:
    path = Path(_DIR.name) / "fuzz.mcap"
    path.write_bytes(data)
    try:
        with BagReader(path) as bag:
            for topic, msgtype, _t, raw in bag.messages():
                bag.deserialize(raw, msgtype, topic=topic)
    except BagError as err:
        assert "\n" not in str(err) and str(path) in str(err)
        event(type(err).__name__ + ": " + str(err).split(": ", 1)[1][:40])
        return
    event("read")
    # The recovery's reader keeps what it can and names the damage; it never raises.
    for _record in ReadableMcap(path).messages():
        pass


@BUDGET
@given(mutated_bytes(_SEEDS["zstd"], keep=len(mc.MAGIC)))
def test_a_damaged_zstd_bag_is_read_or_refused_in_one_line(data: bytes) -> None:
    _read(data)


@BUDGET
@given(mutated_bytes(_SEEDS["lz4"], keep=len(mc.MAGIC)))
def test_a_damaged_lz4_bag_is_read_or_refused_in_one_line(data: bytes) -> None:
    _read(data)


@BUDGET
@given(mutated_bytes(_SEEDS["unindexed"], keep=len(mc.MAGIC)))
def test_a_damaged_unindexed_bag_is_read_or_refused_in_one_line(data: bytes) -> None:
    _read(data)


def test_the_seeds_are_read_whole() -> None:
    """The fuzzers start from bags the reader reads (else they would test refusals only)."""
    for seed in _SEEDS.values():
        path = Path(_DIR.name) / "seed.mcap"
        path.write_bytes(seed)
        with BagReader(path) as bag:
            texts = [bag.deserialize(raw, t).data for _topic, t, _ns, raw in bag.messages()]
        assert texts[:3] == ["hello 0", "hello 1", "hello 2"] or texts == ["m0", "m1", "m2"]
