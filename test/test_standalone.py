"""The repository stands alone: a clone with nothing beside it finds the real maps it ships."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
MAPS = ["esmini_e6mini", "esmini_soderleden", "carla_town04", "carla_town06"]


def test_every_real_map_ships_with_its_attribution():
    readme = (REPO / "data" / "maps" / "README.md").read_text()
    for name in MAPS:
        doc = json.loads((REPO / "data" / "maps" / f"{name}.gt.json").read_text())
        assert doc["features"] and doc["lanes"] and doc["routes"], name
        assert f"`{name}.gt.json`" in readme
    assert "MPL-2.0" in readme and "CC-BY 4.0" in readme and "Computer Vision" in readme


def test_the_tree_names_no_sibling_folder():
    """Nothing the build, the demo or the tests run reads ``../shared``."""
    out = subprocess.run(
        ["git", "grep", "-n", "-e", "../shared", "-e", "shared/data", "--", "Makefile", "scripts", "src", ".ci"],
        cwd=REPO,
        capture_output=True,
        text=True,
    )
    assert out.stdout == "", out.stdout


@pytest.mark.slow
def test_a_clone_alone_loads_the_shipped_maps(tmp_path):
    """The files a clone gets (tracked and new, not ignored: ``git ls-files``), copied to an empty
    folder with no ``shared`` beside it and no $HDMAP_MAPS_DIR, with that copy's source first on the
    path, resolve every map by name from the copy's ``data/maps``."""
    listed = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=REPO, capture_output=True, text=True)
    if listed.returncode:
        pytest.skip("not a git checkout")
    clone = tmp_path / "alone" / "hdmap"
    for rel in listed.stdout.splitlines():
        src = REPO / rel
        if src.is_file() and not src.is_symlink():
            (clone / rel).parent.mkdir(parents=True, exist_ok=True)
            (clone / rel).write_bytes(src.read_bytes())
    code = (
        "import sys; sys.path.insert(0, 'src/hdmap_core')\n"
        "import hdmap_core.simulation.fleet as f\n"
        "assert f.__file__.startswith(sys.argv[1]), f.__file__\n"
        f"for n in {MAPS!r}: print(n, len(f.load_map(n).features))\n"
        "print([str(d) for d in f.maps_dirs()])\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "HDMAP_MAPS_DIR"}
    env["PYTHONPATH"] = ""
    res = subprocess.run([sys.executable, "-c", code, str(clone)], cwd=clone, env=env, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert str(clone / "data" / "maps") in res.stdout
    assert all(f"{n} " in res.stdout for n in MAPS)
