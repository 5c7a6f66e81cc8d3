"""The fuzzers' shared budget, and byte and text mutations of valid inputs."""

from __future__ import annotations

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

#: Every fuzzer runs under these settings. ``derandomize``: examples come from a seed fixed by
#: the test's name, so CI runs the same examples on every run and a failure repeats on any
#: machine (a random seed would find new cases each run but fail CI by chance; hypothesis
#: then prints the failing example to add as an ``@example``). ``database=None``: nothing
#: written to .hypothesis/. ``max_examples`` keeps all the fuzzers together under half a minute
#: on two cores; the deadline (per example) catches a path that scans or allocates for long.
BUDGET = settings(
    max_examples=400,
    deadline=5000,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                           HealthCheck.data_too_large],
)


@st.composite
def mutated_bytes(draw: st.DrawFn, seed: bytes, *, keep: int = 0) -> bytes:
    """``seed`` with a few bytes overwritten, runs inserted or deleted, or cut short (the
    damage of a disk, a copy or a hostile hand), its first ``keep`` bytes (magic) kept."""
    data = bytearray(seed)
    for _ in range(draw(st.integers(1, 6))):
        kind = draw(st.sampled_from(["set", "set8", "insert", "delete", "cut"]))
        low = min(keep, len(data))
        at = draw(st.integers(low, max(len(data) - 1, low)))
        if kind == "set" and at < len(data):
            data[at] = draw(st.integers(0, 255))
        elif kind == "set8" and len(data) >= 8:  # a length or offset made absurd
            at = min(at, len(data) - 8)
            data[at:at + 8] = draw(st.sampled_from(
                [b"\xff" * 8, b"\x00" * 8, (2**31).to_bytes(8, "little"),
                 (2**40).to_bytes(8, "little"), draw(st.binary(min_size=8, max_size=8))]))
        elif kind == "insert":
            data[at:at] = draw(st.binary(min_size=1, max_size=16))
        elif kind == "delete":
            del data[at:at + draw(st.integers(1, 16))]
        elif kind == "cut":
            del data[at:]
    return bytes(data)


#: Snippets that carry YAML's structure, and values the readers must refuse or take.
YAML_SNIPPETS = ["&a ", "*a", "[", "]", "{", "}", ": ", "- ", "\n", "\n  ", "!!python/name:x ",
                 "!!binary ", "1e400", ".nan", "-.inf", "'", '"', "~", "\t", "? ", "|", ">",
                 "#", ",", "0x1F", "2026-01-01", "true", "é", "\x00", "\ufeff", "%YAML 1.1\n",
                 "---\n", "...\n", "<<: *a\n"]


@st.composite
def mutated_text(draw: st.DrawFn, seed: str) -> str:
    """``seed`` with a few YAML snippets or characters inserted, or spans deleted."""
    text = seed
    for _ in range(draw(st.integers(1, 5))):
        at = draw(st.integers(0, len(text)))
        kind = draw(st.sampled_from(["snippet", "char", "delete"]))
        if kind == "snippet":
            text = text[:at] + draw(st.sampled_from(YAML_SNIPPETS)) + text[at:]
        elif kind == "char":
            text = text[:at] + draw(st.characters()) + text[at:]
        else:
            text = text[:at] + text[at + draw(st.integers(1, 40)):]
    return text
