#!/usr/bin/env python3
"""Benchmark of map updating (issue 28), run from the repository: ``hdmap bench --changes``
(``hdmap_ros.commands.bench_changes``, whose docstring says what it measures), with the same
options without their ``--change-`` prefix and the sample bags of this checkout::

    .venv/bin/python scripts/bench_changes.py                      # full
    .venv/bin/python scripts/bench_changes.py --smoke              # CI-sized
    .venv/bin/python scripts/bench_changes.py --section changes --cases shift1.5,restripe --seeds 0,1
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "src/hdmap_core"), str(ROOT / "src/hdmap_ros")]

from hdmap_ros.commands.bench_changes import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main(["--bags", str(ROOT / "bags"), *sys.argv[1:]]))
