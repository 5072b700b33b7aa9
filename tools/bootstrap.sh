#!/usr/bin/env bash
# Bootstrap the project venv: ROS 2 Jazzy wheels, scientific deps, the cwfs_msgs
# interface package (built with plain cmake into the venv prefix) and cwfs_ros
# itself (editable). Idempotent: each step keeps a stamp in .venv/.stamps/ and
# re-runs only when its inputs changed, so a no-op run takes well under 2 s.
#
#   tools/bootstrap.sh            # from anywhere; works on the repo it lives in
#   PYTHON=python3.12 tools/bootstrap.sh
#   BOOTSTRAP_FORCE=1 tools/bootstrap.sh   # ignore stamps, redo every step
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd -P)"  # symlinks resolved: one name
cd "$REPO"

VENV="$REPO/.venv"
VPY="$VENV/bin/python"
STAMPS="$VENV/.stamps"
BUILD_DIR="$REPO/build/msg_defs"
PYTHON="${PYTHON:-python3}"
FORCE="${BOOTSTRAP_FORCE:-0}"

# The ROS wheels' .pth bootstrapper re-executes Python once with the venv's lib/
# on LD_LIBRARY_PATH and marks the whole process tree with this variable. When
# we are started from another ROS venv's Python (e.g. from a test), the venv
# Python below would skip its own re-exec and load the wrong libraries.
unset _ROS_WHEELS_BOOTSTRAP_COMPLETE

say() { printf 'bootstrap: %s\n' "$*"; }
die() { printf 'bootstrap: ERROR: %s\n' "$*" >&2; exit 1; }
trap 'rc=$?; printf "bootstrap: FAILED (exit %s) at line %s: %s\n" "$rc" "$LINENO" "$BASH_COMMAND" >&2' ERR

hash_files() {  # sha256 over the names and contents of the given files, in sorted order
  if [ "$#" -eq 0 ]; then echo none; return; fi
  printf '%s\n' "$@" | LC_ALL=C sort | while IFS= read -r f; do
    printf '%s\n' "$f"; cat -- "$f"
  done | sha256sum | cut -d' ' -f1
}
stamp_ok() {  # stamp_ok NAME HASH -> true when the stamp holds HASH
  [ "$FORCE" != 1 ] && [ -f "$STAMPS/$1" ] && [ "$(cat "$STAMPS/$1")" = "$2" ]
}
stamp_set() { mkdir -p "$STAMPS"; printf '%s\n' "$2" > "$STAMPS/$1"; }
check_version() {  # check_version "3.11" -> fails unless 3.11 <= v <= 3.13
  # 3.11 is the floor of the pinned numpy, scipy, matplotlib and astropy (the ROS wheels
  # would take 3.10); 3.13 the ceiling of the ROS 2 Jazzy wheels.
  case "$1" in
    3.11|3.12|3.13) ;;
    *) die "Python $1 found; cwfs_ros needs Python 3.11-3.13 (set PYTHON=...)" ;;
  esac
}

# 1. venv -------------------------------------------------------------------
# A venv holds its own absolute path (script headers, the editable install, the share/
# links below): one made for another checkout (a copied or moved tree) would run that
# checkout's code, so it is made again.
made_for=""
if [ -f "$STAMPS/repo" ]; then
  made_for="$(cat "$STAMPS/repo")"
elif [ -f "$VENV/bin/activate" ] && ! grep -qF "$VENV" "$VENV/bin/activate"; then
  made_for="another directory (its bin/activate names no $VENV)"  # a venv older than the stamp
fi
if [ -x "$VPY" ] && [ -f "$VENV/pyvenv.cfg" ] && [ -n "$made_for" ] && [ "$made_for" != "$REPO" ]; then
  say "the venv was made for $made_for, not $REPO: making it again"
  rm -rf "$VENV"
fi
if [ -x "$VPY" ] && [ -f "$VENV/pyvenv.cfg" ]; then
  vver="$(sed -n 's/^version[_info]* *= *\([0-9]*\.[0-9]*\).*/\1/p' "$VENV/pyvenv.cfg" | head -n1)"
  check_version "$vver"
  say "venv ok (.venv, Python $vver)"
else
  command -v "$PYTHON" >/dev/null || die "'$PYTHON' not found; install Python 3.11-3.13 or set PYTHON=..."
  pver="$("$PYTHON" -c 'import sys; print("%d.%d" % sys.version_info[:2])')"
  check_version "$pver"
  say "creating .venv with $PYTHON ($pver)"
  rm -rf "$VENV"
  "$PYTHON" -m venv "$VENV" \
    || die "'$PYTHON -m venv' failed (on Debian/Ubuntu: apt-get install python3-venv)"
fi
stamp_set repo "$REPO"

# Every step is constrained by the lock (all transitive versions, tools/lock_requirements.sh),
# which is therefore an input of each step's stamp.
LOCK=requirements/lock.txt
[ -f "$LOCK" ] || die "$LOCK is missing (tools/lock_requirements.sh writes it)"
PIP=("$VPY" -m pip install --disable-pip-version-check --no-input -q -c "$LOCK")

# 2. build backend for the editable install (setuptools) ------------------------
h_build="$(hash_files requirements/build.txt "$LOCK")"
if stamp_ok build "$h_build"; then
  say "build tools ok"
else
  say "installing requirements/build.txt"
  t0=$SECONDS
  "${PIP[@]}" -r requirements/build.txt
  stamp_set build "$h_build"
  say "build tools installed in $((SECONDS - t0)) s"
fi

# 3. ROS 2 wheels (own pip step: pip builds every wheel before installing any) --
h_ros="$(hash_files requirements/ros.txt "$LOCK")"
if stamp_ok ros "$h_ros"; then
  say "ROS wheels ok"
else
  say "installing ROS 2 Jazzy wheels (requirements/ros.txt, ~1 min on a fresh venv)"
  t0=$SECONDS
  "${PIP[@]}" -r requirements/ros.txt
  stamp_set ros "$h_ros"
  say "ROS wheels installed in $((SECONDS - t0)) s"
fi

# 4. scientific and tooling deps --------------------------------------------
h_base="$(hash_files requirements/base.txt "$LOCK")"
if stamp_ok base "$h_base"; then
  say "base requirements ok"
else
  say "installing requirements/base.txt"
  t0=$SECONDS
  "${PIP[@]}" -r requirements/base.txt
  stamp_set base "$h_base"
  say "base requirements installed in $((SECONDS - t0)) s"
fi

# 5. cwfs_msgs interfaces, built with plain cmake into the venv prefix --------
mapfile -t msg_files < <(find msg_defs -type f ! -name '*~' ! -name '*.pyc')
h_msgs="$(printf '%s\n%s\n' "$(hash_files "${msg_files[@]}")" "$h_ros" | sha256sum | cut -d' ' -f1)"
if stamp_ok msgs "$h_msgs" && [ -f "$VENV/share/cwfs_msgs/package.xml" ]; then
  say "cwfs_msgs ok"
else
  say "building cwfs_msgs (msg_defs/ -> build/msg_defs, ~15 s)"
  command -v cmake >/dev/null && { command -v c++ >/dev/null || command -v g++ >/dev/null; } \
    || die "building cwfs_msgs needs cmake and a C/C++ compiler (apt-get install cmake g++)"
  "$VPY" -c 'import sysconfig, os, sys; sys.exit(not os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h")))' \
    || die "building cwfs_msgs needs the Python headers (Python.h; apt-get install python3-dev)"
  # A cache made for another source or venv location (copied tree) cannot be reused.
  if [ -f "$BUILD_DIR/CMakeCache.txt" ] \
     && ! grep -qxF "CMAKE_HOME_DIRECTORY:INTERNAL=$REPO/msg_defs" "$BUILD_DIR/CMakeCache.txt"; then
    rm -rf "$BUILD_DIR"
  fi
  mkdir -p "$BUILD_DIR"
  log="$BUILD_DIR/bootstrap.log"
  t0=$SECONDS
  if ! {
    cmake -S msg_defs -B "$BUILD_DIR" \
      -DCMAKE_INSTALL_PREFIX="$VENV" -DCMAKE_PREFIX_PATH="$VENV" \
      -DPython3_EXECUTABLE="$VPY" -DBUILD_TESTING=OFF \
      && cmake --build "$BUILD_DIR" -j"$(nproc 2>/dev/null || echo 2)" \
      && cmake --install "$BUILD_DIR"
  } >"$log" 2>&1; then
    tail -n 40 "$log" >&2
    die "cwfs_msgs build failed; full log: $log"
  fi
  say "cwfs_msgs built and installed in $((SECONDS - t0)) s"
  stamp_set msgs "$h_msgs"
fi

# 6. cwfs_ros itself, editable ------------------------------------------------
# Inputs: the build files and the set of top-level packages (the editable
# finder maps those when it is installed).
mapfile -t pkg_files < <(
  ls setup.py setup.cfg package.xml 2>/dev/null
  find . -mindepth 2 -maxdepth 2 -name __init__.py -not -path './.venv/*' -not -path './build/*'
)
h_pkg="$(hash_files "${pkg_files[@]}")"
if stamp_ok pkg "$h_pkg" && compgen -G "$VENV/lib/python3*/site-packages/cwfs_ros-*.dist-info" >/dev/null; then
  say "cwfs_ros ok"
else
  say "installing cwfs_ros (editable)"
  "${PIP[@]}" --no-deps --no-build-isolation -e .
  stamp_set pkg "$h_pkg"
fi

# An editable (PEP 660) install skips setup.py's data_files. Link them into the
# venv prefix instead, like `colcon build --symlink-install`, so the ament index
# and share/cwfs_ros/{package.xml,config} resolve as in a ROS install.
link() {  # link TARGET LINKNAME
  if [ -e "$2" ] && [ ! -L "$2" ]; then rm -rf "$2"; fi
  mkdir -p "$(dirname "$2")"
  ln -sfn "$1" "$2"
}
link "$REPO/resource/cwfs_ros" "$VENV/share/ament_index/resource_index/packages/cwfs_ros"
link "$REPO/package.xml" "$VENV/share/cwfs_ros/package.xml"
link "$REPO/config" "$VENV/share/cwfs_ros/config"

say "done"
