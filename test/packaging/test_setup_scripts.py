"""The helpers of scripts/setup.sh: the CMake export fix and the venv .pth hook."""

from __future__ import annotations

import importlib.util
import os
import re
import sys
from pathlib import Path
from types import ModuleType

REPO = Path(__file__).resolve().parents[2]
SCRIPTS = REPO / "scripts"


def _load(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(f"_scripts_{name}", SCRIPTS / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# What a ros-jazzy wheel ships (shortened from std_msgs' export file).
_EXPORT = """\
set_target_properties(std_msgs::std_msgs__rosidl_generator_py PROPERTIES
  INTERFACE_INCLUDE_DIRECTORIES "/opt/python/cp311-cp311/include/python3.11;\
/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include"
  INTERFACE_LINK_LIBRARIES "std_msgs::std_msgs__rosidl_generator_c"
)
"""


def test_fix_rewrites_both_builder_paths_once(tmp_path):
    fix = _load("fix_ros_wheel_cmake")
    path = tmp_path / "export_std_msgs__rosidl_generator_pyExport.cmake"
    path.write_text(_EXPORT)
    assert fix.fix_file(path, py_include="/venv/inc/py", np_include="/venv/np/inc") is True
    text = path.read_text()
    assert "/opt/python" not in text
    assert 'INTERFACE_INCLUDE_DIRECTORIES "/venv/inc/py;/venv/np/inc"' in text
    assert 'INTERFACE_LINK_LIBRARIES "std_msgs::std_msgs__rosidl_generator_c"' in text
    # Idempotent: a second run changes nothing.
    assert fix.fix_file(path, py_include="/venv/inc/py", np_include="/venv/np/inc") is False
    assert path.read_text() == text


def test_fix_leaves_clean_files_untouched(tmp_path):
    fix = _load("fix_ros_wheel_cmake")
    path = tmp_path / "export.cmake"
    clean = 'INTERFACE_INCLUDE_DIRECTORIES "/usr/include/python3.11"\n'
    path.write_text(clean)
    before = path.stat().st_mtime_ns
    assert fix.fix_file(path, py_include="/x", np_include="/y") is False
    assert path.read_text() == clean and path.stat().st_mtime_ns == before


def _make_ws(tmp_path: Path, *, egg_target: Path | None) -> Path:
    ws = tmp_path / "ws"
    pyver = f"python{sys.version_info[0]}.{sys.version_info[1]}"
    site = ws / "install" / "lib" / pyver / "site-packages"
    site.mkdir(parents=True)
    if egg_target is not None:
        egg_target.mkdir(parents=True)
        (site / "hdmap-core.egg-link").write_text(f"{egg_target}\n.")
    return ws


def _run_hook(module_text: str, monkeypatch, env: dict[str, str]) -> dict[str, str]:
    for var in ("PYTHONPATH", "LD_LIBRARY_PATH", "AMENT_PREFIX_PATH", "_ROS_WHEELS_BOOTSTRAP_COMPLETE"):
        monkeypatch.delenv(var, raising=False)
    for var, value in env.items():
        monkeypatch.setenv(var, value)
    exec(compile(module_text, "<hook>", "exec"), {"__name__": "_hdmap_workspace_env"})
    return dict(os.environ)


def test_hook_exports_workspace_and_forces_bootstrap(tmp_path, monkeypatch):
    hook = _load("install_venv_hook")
    build_pkg = tmp_path / "ws" / "build" / "hdmap_core"
    ws = _make_ws(tmp_path, egg_target=build_pkg)
    venv = tmp_path / "venv"
    module, pth = hook.render_hook(ws, venv)
    assert pth == f"import {hook.MODULE_NAME}\n"
    env = _run_hook(module, monkeypatch, {"LD_LIBRARY_PATH": "/venv/lib", "_ROS_WHEELS_BOOTSTRAP_COMPLETE": "1"})
    site = next((ws / "install" / "lib").glob("python*/site-packages"))
    assert env["PYTHONPATH"].split(os.pathsep) == [str(site), str(build_pkg)]
    assert env["LD_LIBRARY_PATH"].split(os.pathsep) == [str(ws / "install" / "lib"), "/venv/lib"]
    assert env["AMENT_PREFIX_PATH"].split(os.pathsep) == [str(ws / "install"), str(venv)]
    # LD_LIBRARY_PATH changed, so the bootstrapper must re-exec this interpreter.
    assert "_ROS_WHEELS_BOOTSTRAP_COMPLETE" not in env


def test_hook_is_a_no_op_when_already_applied(tmp_path, monkeypatch):
    hook = _load("install_venv_hook")
    ws = _make_ws(tmp_path, egg_target=None)
    module, _ = hook.render_hook(ws, tmp_path / "venv")
    first = _run_hook(module, monkeypatch, {})
    keep = {k: first[k] for k in ("PYTHONPATH", "LD_LIBRARY_PATH", "AMENT_PREFIX_PATH")}
    second = _run_hook(module, monkeypatch, {**keep, "_ROS_WHEELS_BOOTSTRAP_COMPLETE": "1"})
    assert {k: second[k] for k in keep} == keep  # nothing duplicated
    assert second["_ROS_WHEELS_BOOTSTRAP_COMPLETE"] == "1"  # no second re-exec: no loop


def test_hook_does_nothing_without_a_built_workspace(tmp_path, monkeypatch):
    hook = _load("install_venv_hook")
    module, _ = hook.render_hook(tmp_path / "never_built", tmp_path / "venv")
    env = _run_hook(module, monkeypatch, {"_ROS_WHEELS_BOOTSTRAP_COMPLETE": "1"})
    assert "PYTHONPATH" not in env and "AMENT_PREFIX_PATH" not in env
    assert env["_ROS_WHEELS_BOOTSTRAP_COMPLETE"] == "1"


def test_hook_sorts_before_the_bootstrapper():
    hook = _load("install_venv_hook")
    assert sorted([hook.BOOTSTRAPPER_PTH, hook.PTH_NAME, "distutils-precedence.pth"])[0] == hook.PTH_NAME


def test_setup_script_is_strict_bash():
    text = (SCRIPTS / "setup.sh").read_text()
    assert text.startswith("#!/usr/bin/env bash\n")
    assert "set -euo pipefail" in text


def test_ci_runs_make_test_then_the_benchmark_smoke_run():
    text = (REPO / ".ci" / "run").read_text()
    assert "set -euo pipefail" in text
    commands = [
        ln.strip()
        for ln in text.splitlines()
        if ln.strip() and not ln.lstrip().startswith(("#", "export", "echo", "cd", "set"))
    ]
    assert commands == ["make test", 'BENCH_SMOKE=1 BENCH_OUT="${BENCH_OUT:-out/ci-bench}" make bench']
    smoke = (SCRIPTS / "bench.sh").read_text().split('if [[ -n "${BENCH_SMOKE:-}" ]]; then', 1)[1].split("fi", 1)[0]
    assert "bench esmini_e6mini" in smoke and "bench_incremental.py" in smoke and "exit 0" in smoke


def test_requirements_pin_every_top_level_package():
    lines = [ln.split("#")[0].strip() for ln in (REPO / "requirements.txt").read_text().splitlines()]
    reqs = [ln for ln in lines if ln and not ln.startswith("-")]
    assert reqs, "requirements.txt lists nothing"
    unpinned = [r for r in reqs if "==" not in r]
    assert unpinned == [], f"unpinned requirements: {unpinned}"
    constraints = (REPO / "constraints.txt").read_text()
    for req in reqs:
        name = req.split("[")[0].split("==")[0]
        version = req.split("==")[1]
        assert f"{name}=={version}" in constraints, f"{req} disagrees with constraints.txt"


def _make_rules() -> dict[str, tuple[list[str], list[str]]]:
    """Makefile target -> (prerequisites, recipe lines with $(VENV)/bin/ dropped)."""
    rules = {}
    pattern = r"^([a-z-]+):([^#\n]*)(?:##[^\n]*)?\n((?:\t[^\n]*\n)*)"
    for m in re.finditer(pattern, (REPO / "Makefile").read_text(), flags=re.M):
        recipe = [ln.strip().replace("$(VENV)/bin/", "") for ln in m.group(3).splitlines()]
        rules[m.group(1)] = (m.group(2).split(), recipe)
    return rules


def test_make_test_lints_before_pytest_with_pinned_tools():
    """``make test`` depends on ``make lint`` (ruff check, ruff format --check, mypy), whose tools
    requirements.txt pins, so CI (``.ci/run``: make test) fails on a lint finding."""
    rules = _make_rules()
    assert "lint" in rules["test"][0] and "lint" not in rules["test-quick"][0]
    assert [ln.split()[:2] for ln in rules["lint"][1]] == [["ruff", "check"], ["ruff", "format"], ["mypy"]]
    assert "--check" in rules["lint"][1][1]
    pins = {ln.split("==")[0] for ln in (REPO / "requirements.txt").read_text().splitlines() if "==" in ln}
    assert {"ruff", "mypy"} <= pins
