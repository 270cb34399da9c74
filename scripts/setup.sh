#!/usr/bin/env bash
# Sets up what the ROS 2 side of pwm_actuator needs, inside the repository:
#   .venv/     a Python 3.11 virtualenv with rclpy (Jazzy) and the build tools, from
#              scripts/requirements-ros.txt pinned by scripts/constraints-ros.txt;
#   .ros-ws/   a colcon workspace (build/, install/, log/) holding the interface package
#              pwm_actuator_msgs built from msg/.
# With `--distro kilted` the same for ROS 2 Kilted, side by side: .venv-kilted/ from
# scripts/requirements-ros-kilted.txt pinned by scripts/constraints-ros-kilted.txt, and
# .ros-ws-kilted/ built with that venv's tools.
# Nothing is written outside the repository except Debian packages (only when one is missing)
# and pip's download cache in $HOME.
#
# Idempotent: each step keeps a stamp with a hash of its inputs and is skipped when they have not
# changed, so a re-run with nothing changed takes about a second. Any change rebuilds that step
# from scratch, so a stale file can never survive it.
#
# Usage: scripts/setup.sh [--distro jazzy|kilted] [--force] [--relock]
#   --distro   which ROS 2 distribution to set up (default jazzy)
#   --force    rebuild the virtualenv and the messages even if nothing changed
#   --relock   reinstall from the requirements file without the lock and rewrite the
#              constraints file from what got installed
# Use the result with `source scripts/env.sh` (Kilted: `PWM_DISTRO=kilted source scripts/env.sh`).

set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# This script by a path that does not depend on how it was called (it is part of the venv hash).
SELF="$REPO/scripts/$(basename "${BASH_SOURCE[0]}")"
MSG_PKG_DIR="$REPO/msg"
MSG_PKG=pwm_actuator_msgs
# The prefix the ROS wheels were built in; their exported CMake targets name include directories
# below it, and CMake refuses include directories that do not exist.
WHEEL_BUILD_PREFIX=/opt/python/cp311-cp311

force=0
force_msgs=0
relock=0
distro=jazzy
while (($#)); do
    case "$1" in
        --force) force=1 ;;
        --rebuild-msgs) force_msgs=1 ;;
        --relock) relock=1; force=1 ;;
        --distro) (($# > 1)) || { echo "setup: --distro needs a value" >&2; exit 2; }
            distro=$2; shift ;;
        --distro=*) distro=${1#--distro=} ;;
        -h | --help) sed -n '2,22p' "$SELF" | sed 's/^# \{0,1\}//'; exit 0 ;;
        *) echo "setup: unknown argument '$1' (try --help)" >&2; exit 2 ;;
    esac
    shift
done

# Jazzy keeps the paths it always had; any other distribution gets its own, suffixed ones.
case "$distro" in
    jazzy) suffix="" ;;
    kilted) suffix="-kilted" ;;
    *) echo "setup: unknown distribution '$distro' (jazzy or kilted)" >&2; exit 2 ;;
esac
VENV="$REPO/.venv$suffix"
WS="$REPO/.ros-ws$suffix"
REQUIREMENTS="$REPO/scripts/requirements-ros$suffix.txt"
CONSTRAINTS="$REPO/scripts/constraints-ros$suffix.txt"
VENV_STAMP="$VENV/.pwm-setup-stamp"
MSGS_STAMP="$WS/.pwm-msgs-stamp"

SECONDS=0
say() { printf 'setup: %s\n' "$*"; }
die() { printf 'setup: error: %s\n' "$*" >&2; exit 1; }

# One setup at a time per checkout: a second one waits, then finds everything up to date.
mkdir -p "$WS"
exec 9>"$WS/setup.lock"
if ! flock -n 9; then
    say "another setup is running in this checkout; waiting for it"
    flock 9
fi

hash_of() {
    # Hash of the given files' names and contents plus any extra words passed after `--`.
    local files=() extra=()
    while (($#)); do
        if [[ "$1" == -- ]]; then shift; extra=("$@"); break; fi
        files+=("$1"); shift
    done
    {
        for f in "${files[@]}"; do
            printf '%s\n' "${f#"$REPO"/}"
            cat "$f"
        done
        printf '%s\n' "${extra[@]}"
    } | sha256sum | cut -d' ' -f1
}

# ---------------------------------------------------------------------------------------------
# 1. System packages: a Python 3.11 with venv and headers, a C/C++ compiler and make.
# ---------------------------------------------------------------------------------------------
find_python() {
    local candidate
    for candidate in python3.11 python3; do
        if command -v "$candidate" >/dev/null 2>&1 &&
            "$candidate" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null
        then
            command -v "$candidate"
            return 0
        fi
    done
    return 1
}

apt_missing=()
want_deb() {
    # want_deb PACKAGE: queue PACKAGE for installation unless dpkg has it already.
    if ! dpkg -s "$1" >/dev/null 2>&1; then apt_missing+=("$1"); fi
}

PYTHON="$(find_python || true)"
if [[ -z "$PYTHON" ]]; then
    # The ROS wheels are built for CPython 3.11, which is Debian 12's python3.
    want_deb python3.11; want_deb python3.11-venv; want_deb python3.11-dev
else
    if ! "$PYTHON" -c 'import venv, ensurepip' >/dev/null 2>&1; then want_deb python3.11-venv; fi
    if ! "$PYTHON" -c 'import os, sys, sysconfig
sys.exit(not os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h")))'; then
        # rosidl_generator_py compiles a C extension against Python.h.
        want_deb python3.11-dev
    fi
fi
command -v cc >/dev/null 2>&1 || want_deb gcc
command -v c++ >/dev/null 2>&1 || want_deb g++
command -v make >/dev/null 2>&1 || want_deb make

if ((${#apt_missing[@]})); then
    say "installing Debian packages: ${apt_missing[*]}"
    sudo_cmd=()
    if [[ "$(id -u)" != 0 ]]; then
        command -v sudo >/dev/null 2>&1 || die "need root or sudo to install: ${apt_missing[*]}"
        sudo_cmd=(sudo)
    fi
    export DEBIAN_FRONTEND=noninteractive
    "${sudo_cmd[@]}" apt-get update -qq
    "${sudo_cmd[@]}" apt-get install -y -qq --no-install-recommends "${apt_missing[@]}" </dev/null
    PYTHON="$(find_python || true)"
fi
[[ -n "$PYTHON" ]] || die "no Python 3.11 found (the ROS $distro wheels are cp311)"
# The interpreter itself, not a launcher shim, so the hash changes if it is replaced.
PYTHON_REAL="$("$PYTHON" -c 'import os, sys; print(os.path.realpath(sys.executable))')"
PYTHON_VERSION="$("$PYTHON" -c 'import platform; print(platform.python_version())')"

# ---------------------------------------------------------------------------------------------
# 2. The virtualenv.
# ---------------------------------------------------------------------------------------------
venv_hash() { hash_of "$REQUIREMENTS" "$CONSTRAINTS" "$SELF" -- "$PYTHON_REAL" "$PYTHON_VERSION"; }
venv_key="$(venv_hash)"
stamp_is() { [[ -f "$1" && "$(cat "$1")" == "$2" ]]; }

map_wheel_prefix() {
    # Points the wheels' exported CMake targets at this venv's Python and numpy headers.
    local pyinc npinc leftovers
    pyinc="$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
    npinc="$("$VENV/bin/python" -c 'import numpy; print(numpy.get_include())')"
    [[ -f "$pyinc/Python.h" ]] || die "Python.h not found in $pyinc"
    [[ -d "$npinc" ]] || die "numpy include directory $npinc not found"
    grep -rlZ --include='*.cmake' -F "$WHEEL_BUILD_PREFIX" "$VENV/share" |
        xargs -0 -r sed -i \
            -e "s#$WHEEL_BUILD_PREFIX/lib/python3\.11/site-packages/numpy/_core/include#$npinc#g" \
            -e "s#$WHEEL_BUILD_PREFIX/include/python3\.11#$pyinc#g"
    # A form not handled above would fail later inside CMake with a less clear message.
    leftovers="$(grep -rl --include='*.cmake' -F "$WHEEL_BUILD_PREFIX" "$VENV/share" || true)"
    [[ -z "$leftovers" ]] || die "unmapped $WHEEL_BUILD_PREFIX paths remain in: $leftovers"
}

write_lock() {
    {
        local relock_cmd="scripts/setup.sh --relock"
        [[ "$distro" == jazzy ]] || relock_cmd="scripts/setup.sh --distro $distro --relock"
        cat <<EOF
# Every package installed into ${VENV#"$REPO"/}/ by scripts/setup.sh, pinned, so that a fresh clone gets the
# same set as the one last checked. Used as \`pip install -r ${REQUIREMENTS##*/} -c <this file>\`.
# Regenerate after changing ${REQUIREMENTS##*/} with \`$relock_cmd\`.
EOF
        "$VENV/bin/python" - <<'EOF'
from importlib import metadata

rows = set()
for dist in metadata.distributions():
    # Only what pip installed: the ROS wheels also carry egg-info folders of their own.
    if (dist.read_text("INSTALLER") or "").strip() != "pip":
        continue
    name = dist.metadata["Name"].lower().replace("_", "-")
    if name not in ("pip", "setuptools"):
        rows.add(f"{name}=={dist.version}")
print("\n".join(sorted(rows)))
EOF
    } >"$CONSTRAINTS.tmp"
    mv "$CONSTRAINTS.tmp" "$CONSTRAINTS"
}

venv_built=0
if ((force)) || [[ ! -x "$VENV/bin/python" ]] || ! stamp_is "$VENV_STAMP" "$venv_key"; then
    step_start=$SECONDS
    say "creating $VENV with $PYTHON_REAL ($PYTHON_VERSION)"
    rm -rf -- "$VENV"
    "$PYTHON" -m venv "$VENV"
    pip_args=(--disable-pip-version-check --no-input --quiet -r "$REQUIREMENTS")
    ((relock)) || pip_args+=(-c "$CONSTRAINTS")
    say "installing pinned packages from ${REQUIREMENTS#"$REPO"/}"
    "$VENV/bin/python" -m pip install "${pip_args[@]}" </dev/null
    map_wheel_prefix
    if ((relock)); then
        write_lock
        say "wrote ${CONSTRAINTS#"$REPO"/}"
        venv_key="$(venv_hash)"
    fi
    printf '%s\n' "$venv_key" >"$VENV_STAMP"
    venv_built=1
    say "virtualenv ready ($((SECONDS - step_start)) s)"
else
    say "virtualenv up to date"
fi

# ---------------------------------------------------------------------------------------------
# 3. The interface package pwm_actuator_msgs, built with colcon into .ros-ws/ (or its
#    distribution's .ros-ws-NAME/).
# ---------------------------------------------------------------------------------------------
msg_files=("$MSG_PKG_DIR/package.xml" "$MSG_PKG_DIR/CMakeLists.txt")
while IFS= read -r -d '' f; do msg_files+=("$f"); done \
    < <(find "$MSG_PKG_DIR" -maxdepth 2 \( -name '*.msg' -o -name '*.action' \) -print0 |
        LC_ALL=C sort -z)
((${#msg_files[@]} > 2)) || die "no .msg files in $MSG_PKG_DIR"
msgs_key="$(hash_of "${msg_files[@]}" -- "$venv_key")"

build_msgs() {
    local step_start=$SECONDS
    say "building $MSG_PKG from msg/ with colcon"
    rm -rf -- "$WS/build" "$WS/install" "$WS/log" "$MSGS_STAMP"
    # Only the venv as prefix; COLCON_HOME inside the workspace so no personal colcon defaults
    # (~/.colcon) change the build.
    if ! (
        cd "$REPO"
        unset PYTHONPATH LD_LIBRARY_PATH CMAKE_PREFIX_PATH AMENT_PREFIX_PATH COLCON_PREFIX_PATH
        # shellcheck disable=SC2030  # for colcon and cmake in this subshell only
        export PATH="$VENV/bin:$PATH" VIRTUAL_ENV="$VENV"
        export AMENT_PREFIX_PATH="$VENV" CMAKE_PREFIX_PATH="$VENV" COLCON_HOME="$WS/colcon-home"
        "$VENV/bin/colcon" --log-base "$WS/log" --log-level error build \
            --base-paths "$MSG_PKG_DIR" \
            --build-base "$WS/build" --install-base "$WS/install" \
            --event-handlers console_cohesion+ \
            --cmake-args -DPython3_EXECUTABLE="$VENV/bin/python" -DBUILD_TESTING=OFF \
            </dev/null >"$WS/colcon-build.out" 2>&1
    ); then
        cat "$WS/colcon-build.out" >&2
        die "colcon build of $MSG_PKG failed (full log in ${WS#"$REPO"/}/log/)"
    fi
    printf '%s\n' "$msgs_key" >"$MSGS_STAMP"
    say "$MSG_PKG built ($((SECONDS - step_start)) s)"
}

if ((force || force_msgs || venv_built)) || [[ ! -d "$WS/install/$MSG_PKG" ]] ||
    ! stamp_is "$MSGS_STAMP" "$msgs_key"; then
    build_msgs
    msgs_built=1
else
    say "$MSG_PKG up to date"
    msgs_built=0
fi

# ---------------------------------------------------------------------------------------------
# 4. Check that the result is usable: rclpy loads, the RMW loads, the messages import.
# ---------------------------------------------------------------------------------------------
verify() {
    (
        # shellcheck source=scripts/env.sh
        PWM_DISTRO="$distro" source "$REPO/scripts/env.sh"
        export ROS_LOG_DIR="$WS/ros_log"
        python - <<'EOF'
import rclpy
from rclpy.context import Context
from pwm_actuator_msgs.msg import ChannelParams, ChannelStatus, OutputEdge, ValveState

for cls in (ChannelParams, ChannelStatus, OutputEdge, ValveState):
    # Serialising needs the generated C type support, not just the Python module.
    from rclpy.serialization import deserialize_message, serialize_message
    assert deserialize_message(serialize_message(cls()), cls) == cls()
# Loading the RMW implementation is the step that fails when a library is missing.
context = Context()
rclpy.init(context=context, domain_id=0)
rclpy.shutdown(context=context)
EOF
    )
}

if ! verify >"$WS/verify.out" 2>&1; then
    # Something was changed or removed behind the stamps' back: rebuild the messages first,
    # then everything, before giving up.
    if ((!msgs_built)); then
        say "the existing environment does not work; rebuilding $MSG_PKG"
        exec "$SELF" --distro "$distro" --rebuild-msgs
    fi
    if ((!venv_built)); then
        say "the environment still does not work; rebuilding the virtualenv too"
        exec "$SELF" --distro "$distro" --force
    fi
    cat "$WS/verify.out" >&2
    die "the freshly built environment does not work (see above)"
fi
if [[ "$distro" == jazzy ]]; then
    say "ready: rclpy and $MSG_PKG import (${SECONDS} s); use it with 'source scripts/env.sh'"
else
    say "ready ($distro): rclpy and $MSG_PKG import (${SECONDS} s); use it with" \
        "'PWM_DISTRO=$distro source scripts/env.sh'"
fi
