"""The offset model read for many drives at once (hdmap_core.pipeline.offset_table): the same
values as ``OffsetModel.offset`` drive by drive, to the last bit."""

from __future__ import annotations

import numpy as np

from hdmap_core.live.tiles import _ClippedOffsets
from hdmap_core.pipeline.adjustment import DriveOffset, OffsetModel
from hdmap_core.pipeline.driver import _shift_fn


def _model() -> OffsetModel:
    rng = np.random.default_rng(3)
    drives = {
        "a": DriveOffset(k0=2, bias_m=0.31, drift_m=rng.normal(0.0, 0.4, 7)),
        "b": DriveOffset(k0=0, bias_m=-0.12, drift_m=np.zeros(0)),  # bias only
        "c": DriveOffset(k0=-3, bias_m=0.05, drift_m=rng.normal(0.0, 0.4, 2)),
        "d": DriveOffset(k0=11, bias_m=1.7, drift_m=rng.normal(0.0, 0.4, 30)),
    }
    return OffsetModel(
        knot_spacing_m=25.0, correlation_length_m=150.0, drift_sigma_m=0.3, bias_sigma_m=1.0, drives=drives
    )


def _samples(ids: tuple[str, ...], n: int = 4000) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(5)
    # distances before, inside and beyond every curve's knots (the decay outside)
    return rng.integers(0, len(ids), n), rng.uniform(-400.0, 1400.0, n)


def _per_drive(model, ids, drive, s):
    out = np.zeros(len(drive))
    for i, did in enumerate(ids):
        sel = drive == i
        out[sel] = model.offset(did, s[sel])
    return out


def test_table_gives_the_models_offsets_bit_for_bit():
    model = _model()
    ids = ("d", "x", "a", "b", "c")  # "x": not in the model, offset 0
    drive, s = _samples(ids)
    got = model.table(ids).offset(drive, s)
    want = _per_drive(model, ids, drive, s)
    assert np.array_equal(got, want)
    assert np.all(got[drive == 1] == 0.0)
    assert np.all(got[drive == 3] == -0.12)
    assert model.table(ids).offset(np.zeros(0, np.int64), np.zeros(0)).shape == (0,)


def test_clipped_table_reads_from_the_clip_starts():
    model = _model()
    ids = ("a", "c", "d", "x")
    clipped = _ClippedOffsets(model, {"a": 130.5, "d": 977.25, "x": 3.0})  # "c": not clipped
    drive, s = _samples(ids)
    got = clipped.table(ids).offset(drive, s)
    assert np.array_equal(got, _per_drive(clipped, ids, drive, s))
    # a clip of a clip is read drive by drive (its sums would be in another order)
    assert _ClippedOffsets(clipped, {"a": 1.0}).table(ids) is None


class _NoTable:
    """An offset source without a table: read drive by drive."""

    def offset(self, drive_id: str, s_m: np.ndarray) -> np.ndarray:
        return np.full(np.shape(s_m), {"a": 0.5}.get(drive_id, -0.25))

    def table(self, drive_ids: tuple[str, ...]) -> None:
        return None


def test_shift_fn_reads_the_table_or_drive_by_drive():
    model = _model()
    ids = ("b", "a", "d")
    drive, s = _samples(ids, 500)
    assert np.array_equal(_shift_fn(model, ids)(drive, s), _per_drive(model, ids, drive, s))
    got = _shift_fn(_NoTable(), ids)(drive, s)
    assert np.array_equal(got, np.where(drive == 1, 0.5, -0.25))
