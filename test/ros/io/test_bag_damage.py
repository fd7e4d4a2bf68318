"""Hostile bags: a chunk failing its CRC is skipped and the rest read; a drive recorded with another
definition is rejected per message; random mutations of a small bag never give a traceback or a
hang (fuzz with a fixed seed)."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from hdmap_core.errors import BagError
from hdmap_core.pipeline.driver import prepare_drives
from hdmap_core.pipeline.preprocess import preprocess
from hdmap_ros.io.bagio import (
    iter_bag,
    read_fleet_bag,
    write_fleet_bag,
)

from bag_samples import assert_drives_equal
from hostile_bags import ORIGIN, bag_without_vehicle_id, crc_mcap, rechunk, small_drives, two_definition_bag


def _chunks(path: Path) -> list[tuple[int, int]]:
    with path.open("rb") as f:
        return [(c.chunk_start_offset, c.chunk_length) for c in make_reader(f).get_summary().chunk_indexes]


def _flip(path: Path, offset: int) -> None:
    data = bytearray(path.read_bytes())
    data[offset] ^= 0xFF
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("which", [0, 1])
def test_a_chunk_failing_its_crc_is_skipped_and_the_rest_read(tmp_path, which):
    drives = small_drives(12)
    path = crc_mcap(tmp_path / "crc.mcap", drives)
    chunks = _chunks(path)
    assert len(chunks) >= 4
    start, length = chunks[which]
    _flip(path, start + length - 20)  # inside the chunk's records: its CRC fails
    got = read_fleet_bag(path)
    assert got.error is None and got.origin == (None if which == 0 else ORIGIN)  # the first chunk holds the origin
    assert [r.reason for r in got.rejected] == ["damaged_chunk"]
    assert "CRC" in got.rejected[0].detail or "crc" in got.rejected[0].detail
    ids = [d.drive_id for d in got.drives]
    assert 0 < len(ids) < len(drives) and ids[-1] == drives[-1].drive_id  # the chunks after it are read
    for d in got.drives:
        assert_drives_equal(d, drives[int(d.drive_id[1:])])


def test_a_rosbag2_directory_with_a_bad_chunk_goes_on_past_it(tmp_path):
    drives = small_drives(12)
    bag = write_fleet_bag(tmp_path / "fleet", drives, ORIGIN)
    (mcap,) = bag.glob("*.mcap")
    rechunk(mcap)  # small chunks with CRCs, as ros2 bag record writes them
    start, length = _chunks(mcap)[1]
    _flip(mcap, start + length - 20)
    got = read_fleet_bag(bag)
    assert got.error is None and "damaged_chunk" in {r.reason for r in got.rejected}
    assert got.drives[-1].drive_id == drives[-1].drive_id and len(got.drives) < len(drives)
    assert len({d.drive_id for d in got.drives}) == len(got.drives)  # nothing delivered twice


def test_a_drive_of_another_definition_is_rejected_per_message(tmp_path):
    drives = small_drives(3)
    got = read_fleet_bag(bag_without_vehicle_id(tmp_path, drives))
    assert got.error is None and not got.drives and got.origin == ORIGIN
    assert [(r.drive_id, r.reason) for r in got.rejected] == [(d.drive_id, "definition_mismatch") for d in drives]
    assert "vehicle_id" in got.rejected[0].detail


@pytest.mark.parametrize("rosbag2", [False, True], ids=["mcap", "rosbag2"])
def test_two_definitions_of_one_type_keep_the_good_drives_and_reject_the_others(tmp_path, rosbag2):
    """One /fleet/drives connection with the contract's Drive, one without ``vehicle_id``. A bare MCAP
    holds both schemas: each connection is decoded with its own. rosbag2 holds one definition per
    type (its MCAP storage writes one schema per type name) but each connection's type hash: the
    connection whose hash is not that of the definition in the bag is rejected per message."""
    drives = small_drives(8)
    good, bad = drives[0::2], drives[1::2]  # interleaved in the bag
    path = two_definition_bag(tmp_path / ("two" if rosbag2 else "two.mcap"), good, bad, rosbag2=rosbag2)
    got = read_fleet_bag(path)
    assert got.error is None and got.origin == ORIGIN
    assert [d.drive_id for d in got.drives] == [d.drive_id for d in good]
    for d, want in zip(got.drives, good, strict=True):
        assert_drives_equal(d, want)
    assert [(r.drive_id, r.reason) for r in got.rejected] == [(d.drive_id, "definition_mismatch") for d in bad]
    assert all(r.topic == "/fleet/drives" for r in got.rejected)
    assert all(("hash" if rosbag2 else "vehicle_id") in r.detail for r in got.rejected)
    messages = list(iter_bag(path, topics=("/fleet/drives",)))
    if rosbag2:
        assert [bool(bm.unknown_definition) for bm in messages] == [i % 2 == 1 for i in range(len(drives))]
    else:  # each channel's messages come with their own schema's types
        assert len({bm.typestore for bm in messages}) == 2


# ----------------------------------------------------------------------------------------- fuzz


def _mutate(data: bytes, rng: np.random.Generator) -> bytes:
    b = bytearray(data)
    kind = rng.integers(6)
    if kind == 0:  # flip a few bytes
        for _ in range(int(rng.integers(1, 8))):
            b[int(rng.integers(len(b)))] ^= int(rng.integers(1, 256))
    elif kind == 1:  # truncate
        del b[int(rng.integers(8, len(b))) :]
    elif kind == 2:  # a run of random bytes
        at, n = int(rng.integers(len(b))), int(rng.integers(1, 64))
        b[at : at + n] = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
    elif kind == 3:  # a large length field: 0xff bytes
        at = int(rng.integers(len(b) - 8))
        b[at : at + 8] = b"\xff" * 8
    elif kind == 4:  # delete a span
        at = int(rng.integers(len(b)))
        del b[at : at + int(rng.integers(1, 200))]
    else:  # duplicate a span
        at = int(rng.integers(len(b)))
        b[at:at] = b[at : at + int(rng.integers(1, 200))]
    return bytes(b)


@pytest.mark.slow
def test_fuzz_random_mutations_give_no_traceback_and_no_hang(tmp_path):
    """300 mutations of a small bag (a rosbag2 directory: its .mcap, sometimes its metadata.yaml;
    a bare .mcap with CRCs and small chunks): every read ends with drives, rejections or a
    BagError, in bounded time, and the drives read go through the pipeline's input stage
    (~20 s: the rosbag2 reader takes ~0.1 s per open)."""
    drives = small_drives(4, n=30)
    bag = write_fleet_bag(tmp_path / "seed", drives, ORIGIN)
    (mcap,) = bag.glob("*.mcap")
    bare = crc_mcap(tmp_path / "seed.mcap", drives, chunk_size=2_000)
    originals = {"mcap": mcap.read_bytes(), "yaml": (bag / "metadata.yaml").read_bytes(), "bare": bare.read_bytes()}
    rng = np.random.default_rng(20261206)
    work = tmp_path / "work"
    outcomes: dict[str, int] = {}
    slowest = 0.0
    for _ in range(300):
        target = ("mcap", "bare", "yaml")[int(rng.choice(3, p=[0.45, 0.45, 0.1]))]
        shutil.rmtree(work, ignore_errors=True)
        shutil.copytree(bag, work)
        path = work if target != "bare" else work / "bare.mcap"
        if target == "bare":
            path.write_bytes(_mutate(originals["bare"], rng))
        elif target == "mcap":
            (work / mcap.name).write_bytes(_mutate(originals["mcap"], rng))
        else:
            (work / "metadata.yaml").write_bytes(_mutate(originals["yaml"], rng))
        t0 = time.perf_counter()
        got = read_fleet_bag(path)  # any exception other than the documented ones fails the test
        try:
            list(iter_bag(path))
        except BagError:
            pass
        usable, _ = prepare_drives(got.drives)  # what the pipeline does first (issue: IndexError there)
        if usable:
            preprocess(usable)
        slowest = max(slowest, time.perf_counter() - t0)
        key = "error" if got.error else ("rejections" if got.rejected else "clean")
        outcomes[key] = outcomes.get(key, 0) + 1
    assert slowest < 10.0, f"a read took {slowest:.1f} s"
    assert outcomes.get("error", 0) > 0 and outcomes.get("rejections", 0) > 0  # the mutations did hit
