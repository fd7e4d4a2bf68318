"""The markings' move followed cut by cut (``evidence._follow_move``) is the recursion its
docstring states: on each cut the median of the finite moves within reach of the move so far
pulls it half way. Checked against that recursion written plainly with ``np.median`` (the fast
one sorts a few values itself), bit for bit, on odd and even counts, NaN and empty cuts."""

from __future__ import annotations

import numpy as np
import pytest

from hdmap_core.updates.evidence import _follow_move


def _plain(cut: np.ndarray, move: np.ndarray, k: int, reach_m: float) -> np.ndarray:
    out, m = np.zeros(k), 0.0
    for c in range(k):
        v = move[cut == c]
        v = v[np.isfinite(v) & (np.abs(v - m) <= reach_m)]
        if len(v):
            m += 0.5 * (float(np.median(v)) - m)
        out[c] = m
    return out


@pytest.mark.parametrize("seed", range(20))
def test_follow_move_is_the_plain_recursion_bit_for_bit(seed):
    rng = np.random.default_rng(seed)
    k = int(rng.integers(1, 400))
    n = int(rng.integers(0, 1500))
    cut = np.sort(rng.integers(0, k, n))
    move = rng.normal(0.5, 1.5, n)
    move[rng.random(n) < 0.05] = np.nan
    got = _follow_move(cut, move, k, 1.0)
    assert np.array_equal(got, _plain(cut, move, k, 1.0))


def test_follow_move_follows_a_taper_and_keeps_it_over_empty_cuts():
    # moves growing by 0.1 m per cut up to 2 m, then nothing seen for 10 cuts, then 2 m again
    k = 40
    cut = np.r_[np.repeat(np.arange(20), 3), np.repeat(np.arange(30, 40), 3)]
    move = np.r_[np.repeat(np.minimum(0.1 * np.arange(1, 21), 2.0), 3), np.full(30, 2.0)]
    out = _follow_move(cut, move, k, 0.5)
    assert out[0] == pytest.approx(0.05)
    assert np.all(np.diff(out[:20]) > 0)  # it follows the taper
    assert np.all(out[20:30] == out[19])  # a cut with none keeps it
    assert out[-1] == pytest.approx(2.0, abs=0.01)
