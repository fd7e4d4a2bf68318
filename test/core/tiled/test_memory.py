"""Tests of hdmap_core.tiled.memory: trim_memory gives freed heap pages back to the OS."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from hdmap_core.tiled.memory import rss_mb, trim_memory


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc malloc_trim, /proc RSS")
def test_trim_memory_returns_a_fragmented_heap():
    # 8 kB arrays live in the heap (below the mmap threshold); keeping every 50th one leaves it
    # fragmented, so free() alone cannot shrink it
    arrays = [np.ones(1000) for _ in range(40000)]  # about 330 MB
    kept = arrays[::50]
    del arrays
    before = rss_mb()
    assert trim_memory() is True
    assert rss_mb() < before - 100.0
    assert all(a[0] == 1.0 for a in kept)  # what is still referenced is untouched
