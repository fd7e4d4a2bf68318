#!/usr/bin/env bash
# One-command setup of the hdmap workspace (what `make setup` runs). Idempotent; no root needed.
#
#   1. creates .venv (python3 -m venv; Python 3.11, what the ros-jazzy wheels are built for),
#   2. pip installs the pinned requirements (requirements.txt + constraints.txt): ROS 2 Jazzy from
#      the PyPI wheels, colcon, numpy & co.,
#   3. fixes the wheels' CMake exports (scripts/fix_ros_wheel_cmake.py, inside .venv only),
#   4. colcon-builds src/ (hdmap_msgs, hdmap_core, hdmap_ros) into install/ (--symlink-install,
#      so edits to the Python sources are live without a rebuild),
#   5. installs a .pth hook into .venv so that every .venv Python sees the built workspace with
#      nothing sourced, and links the executables (hdmap, the nodes) into .venv/bin.
#
# Each step is skipped when its inputs did not change since it last succeeded (stamp files in
# .venv and install/). Environment: PYTHON (interpreter for a new venv, default python3),
# HDMAP_FORCE=1 (redo every step).
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd -P)"
VENV="$ROOT/.venv"
PY="$VENV/bin/python"
PYTHON="${PYTHON:-python3}"
FORCE="${HDMAP_FORCE:-0}"
cd "$ROOT"

say() { printf '[setup] %s\n' "$*"; }
die() { printf '[setup] error: %s\n' "$*" >&2; exit 1; }
hash_of() { sha256sum | cut -d' ' -f1; }
took() { local now; now=$(date +%s); say "  ($(( now - t_step )) s)"; t_step=$now; }
# pip prints one warning per package for this machine's empty local mirror indexes: drop them.
quiet_pip() { { grep -v -E "^WARNING: Location 'file:.*' is ignored" || true; }; }

start=$(date +%s)
t_step=$start

# --- 1. virtual environment ------------------------------------------------------------------
if [[ ! -x "$PY" ]]; then
    command -v "$PYTHON" >/dev/null || die "no '$PYTHON' on PATH: install Python 3.11 or set PYTHON=/path/to/python3.11"
    "$PYTHON" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' \
        || die "$PYTHON is $("$PYTHON" -V 2>&1); the ros-jazzy wheels need Python 3.11 (set PYTHON=...)"
    say "creating $VENV"
    "$PYTHON" -m venv "$VENV"
    took
fi
"$PY" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null \
    || die "$VENV is broken or not Python 3.11: move it away and run make setup again"
PYVER=python3.11
SITE="$VENV/lib/$PYVER/site-packages"

# --- 2. pinned Python packages ---------------------------------------------------------------
pip_hash=$(cat requirements.txt constraints.txt <("$PY" -VV) | hash_of)
pip_stamp="$VENV/.hdmap-pip.stamp"
if [[ "$FORCE" == 1 || "$(cat "$pip_stamp" 2>/dev/null)" != "$pip_hash" \
      || ! -x "$VENV/bin/colcon" || ! -f "$SITE/ros_wheels_bootstrapper.pth" ]]; then
    say "installing pinned Python packages (ROS 2 Jazzy wheels, colcon, numpy, ...)"
    # -c: constraints.txt is named inside requirements.txt as well; repeating it is harmless.
    "$PY" -m pip install --disable-pip-version-check --progress-bar off -q \
        -r requirements.txt -c constraints.txt 2>&1 | quiet_pip
    echo "$pip_hash" > "$pip_stamp"
    took
    rm -f "$ROOT/install/.hdmap-build.stamp"   # new packages: rebuild the workspace
else
    say "Python packages up to date"
fi

# --- 3. the wheels' CMake quirk (idempotent, cheap) -------------------------------------------
"$PY" "$ROOT/scripts/fix_ros_wheel_cmake.py"

# --- 4. colcon build ---------------------------------------------------------------------------
# What the build depends on: every file under src/ except the Python package sources themselves
# (--symlink-install makes those live) plus colcon.meta and the installed packages.
build_hash=$(
    {
        find src -type f ! -path '*/__pycache__/*' \
            ! -path 'src/hdmap_core/hdmap_core/*' ! -path 'src/hdmap_ros/hdmap_ros/*' \
            -printf '%p %T@ %s\n' | LC_ALL=C sort
        cat colcon.meta "$pip_stamp"
        echo "$ROOT"
    } | hash_of
)
build_stamp="$ROOT/install/.hdmap-build.stamp"
if [[ "$FORCE" == 1 || "$(cat "$build_stamp" 2>/dev/null)" != "$build_hash" ]]; then
    say "colcon build (hdmap_msgs, hdmap_core, hdmap_ros)"
    # Only the venv is the ROS underlay: keep a sourced /opt/ros or an older workspace out.
    env -u PYTHONPATH -u LD_LIBRARY_PATH -u COLCON_PREFIX_PATH -u _ROS_WHEELS_BOOTSTRAP_COMPLETE \
        AMENT_PREFIX_PATH="$VENV" CMAKE_PREFIX_PATH="$VENV" PATH="$VENV/bin:$PATH" \
        "$VENV/bin/colcon" build --merge-install --symlink-install --base-paths src \
        2>&1 | { grep -v -E "doesn't contain any 'local_setup\.\*' files|byte-compiling is disabled" || true; }
    echo "$build_hash" > "$build_stamp"
    took
else
    say "workspace build up to date (install/)"
fi

# --- 5. nothing to source: .pth hook + executables in .venv/bin --------------------------------
"$PY" "$ROOT/scripts/install_venv_hook.py" "$ROOT"
for exe in "$ROOT"/install/lib/hdmap_ros/*; do
    [[ -x "$exe" && -f "$exe" ]] || continue
    ln -sfn "$exe" "$VENV/bin/$(basename "$exe")"
done

# Smoke test from another directory with a clean environment: what a newcomer will do.
# ROS + the built messages are this script's job (fatal); the CLI is code (a warning: the test
# suite then says exactly what is broken).
clean_run() { (cd / && env -i HOME="${HOME:-/tmp}" PATH=/usr/bin:/bin "$@"); }
clean_run "$PY" -c 'import rclpy; from hdmap_msgs.msg import Drive, Map' \
    || die "rclpy / hdmap_msgs do not import from a clean environment (see above)"
clean_run "$VENV/bin/hdmap" --help >/dev/null \
    || say "warning: setup is complete, but .venv/bin/hdmap --help fails (a code error, see above)"

say "done in $(( $(date +%s) - start )) s: try  .venv/bin/hdmap --help   or   make test"
