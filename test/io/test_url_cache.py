"""Inputs named by URL (io/url_cache.py): a rosbag2 directory and single files fetched over
HTTP on loopback into the cache with their layout, kept while unchanged and fetched again
once changed; paths and file:// URLs read in place; one-line refusals naming the URL."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from helpers_http import served

from lidarcal_ros.errors import InputError
from lidarcal_ros.io.url_cache import CACHE_ENV, is_url, local_source, source_of


@pytest.fixture()
def cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))
    return tmp_path / "cache"


@pytest.fixture()
def site(tmp_path: Path) -> Path:
    """A rosbag2-like directory and a lone file to serve."""
    root = tmp_path / "site"
    (root / "flight").mkdir(parents=True)
    (root / "flight" / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    (root / "flight" / "flight_0.mcap").write_bytes(os.urandom(300_000))
    (root / "strip_1.laz").write_bytes(os.urandom(5_000))
    return root


def _gets(requests: list[tuple[str, str]], name: str) -> int:
    return sum(1 for method, path in requests if method == "GET" and path.endswith(name))


def test_urls_and_paths_told_apart() -> None:
    assert is_url("s3://bucket/flight") and is_url("https://host/a.mcap")
    assert not is_url("flight") and not is_url("/data/flight.mcap") and not is_url("c:/x")
    assert not is_url(Path("s3://bucket"))  # (a Path is a path: "s3:/bucket")
    assert source_of("s3://bucket/flight") == "s3://bucket/flight"
    assert source_of("data/flight") == Path("data/flight")


def test_a_bag_directory_is_copied_with_its_layout_and_kept_while_unchanged(
        site: Path, cache: Path) -> None:
    with served(site) as (base, requests):
        local = local_source(f"{base}/flight", what="bag")
        assert local.name == "flight" and local.is_relative_to(cache)
        assert sorted(p.name for p in local.iterdir()) == ["flight_0.mcap", "metadata.yaml"]
        for name in ("flight_0.mcap", "metadata.yaml"):
            assert (local / name).read_bytes() == (site / "flight" / name).read_bytes()
        assert _gets(requests, "flight_0.mcap") == 1
        # again: the copy kept (listed, not fetched)
        assert local_source(f"{base}/flight", what="bag") == local
        assert _gets(requests, "flight_0.mcap") == 1
        # the source changed: fetched again
        (site / "flight" / "flight_0.mcap").write_bytes(os.urandom(200_000))
        local_source(f"{base}/flight", what="bag")
        assert _gets(requests, "flight_0.mcap") == 2
        assert (local / "flight_0.mcap").read_bytes() == \
            (site / "flight" / "flight_0.mcap").read_bytes()
    assert not list(local.glob(".*partial"))


def test_a_file_keeps_its_name_and_urls_do_not_share_copies(site: Path, cache: Path) -> None:
    with served(site) as (base, _):
        local = local_source(f"{base}/strip_1.laz", what="LAS file")
        bag = local_source(f"{base}/flight", what="bag")
        signed = local_source(f"{base}/strip_1.laz?signature=x%2Fy", what="LAS file")
    assert local.name == "strip_1.laz" and local.read_bytes() == (site / "strip_1.laz").read_bytes()
    assert local.parent != bag.parent
    # (a query, a signed link's, is no part of the name: the readers go by its suffix)
    assert signed.name == "strip_1.laz" and signed.read_bytes() == local.read_bytes()


def test_paths_and_file_urls_are_read_in_place(site: Path, cache: Path) -> None:
    assert local_source(site / "flight", what="bag") == site / "flight"
    assert local_source(str(site / "flight"), what="bag") == site / "flight"
    assert local_source((site / "flight").as_uri(), what="bag") == site / "flight"
    assert not cache.exists()


def test_refusals_are_one_line_naming_the_url(site: Path, cache: Path) -> None:
    with served(site) as (base, _):
        with pytest.raises(InputError, match=r"^bag http://127\.0\.0\.1:\d+/nothing: not found$"):
            local_source(f"{base}/nothing", what="bag")
    with pytest.raises(InputError, match=r"^bag nosuch://x/y: no filesystem for this URL here"):
        local_source("nosuch://x/y", what="bag")
    # (the server is gone: nothing listens on its port)
    with pytest.raises(InputError, match=r"^bag http://127\.0\.0\.1:\d+/flight: cannot be "
                                         r"fetched \(.+\)$"):
        local_source(f"{base}/flight", what="bag")
    assert not cache.exists() or not any(cache.iterdir())  # (no trace of what was refused)
