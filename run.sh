#!/usr/bin/env bash
# gcn_match_ros entry point.
#
#   ./run.sh setup              create/refresh .venv, build messages, install the package
#   ./run.sh test [pytest args] setup, then python -m pytest test/ -q [args]
#   ./run.sh demo [args]        setup, then python -m gcn_match_ros.ros.demo [args]
#   ./run.sh CMD [args]         setup, then run CMD inside the environment
#                               (e.g. ./run.sh gcn-match eval ..., ./run.sh python ...)
#
# Environment:
#   PYTHON          interpreter used to create .venv (default: python3.11)
#   TORCH_WHEEL_DIR directory holding the torch CPU wheel (default: /opt/wheels)
#   ROS_DOMAIN_ID   kept if set; `test` otherwise picks a random one in 1..100
#   ROS_LOG_DIR     kept if set; otherwise a temporary dir (test) or log/ros (others)
# ROS discovery is always confined to this machine (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST).
# See docs/setup.md.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
VENV="$ROOT/.venv"
PYTHON="${PYTHON:-python3.11}"
TORCH_VERSION="2.13.0"
TORCH_WHEEL_DIR="${TORCH_WHEEL_DIR:-/opt/wheels}"
STAMP="$VENV/.gcn_match_ros-setup.stamp"
MSG_BUILD="$ROOT/build/gcn_match_msgs"
SETUP_LOG="$ROOT/build/setup.log"

export PIP_NO_INPUT=1 PIP_PROGRESS_BAR=off PIP_DISABLE_PIP_VERSION_CHECK=1

log() { echo "[setup] $*" >&2; }
die() { echo "[setup] ERROR: $*" >&2; exit 1; }

usage() {
    sed -n '2,16p' "${BASH_SOURCE[0]}" | sed 's/^# \{0,1\}//'
}

# Run a set-up step quietly; on failure show the end of its output and stop.
step() {
    local what="$1"; shift
    log "$what"
    if ! "$@" >>"$SETUP_LOG" 2>&1; then
        echo "[setup] ERROR: '$what' failed; last lines of $SETUP_LOG:" >&2
        grep -v "is ignored: it is neither a file nor a directory" "$SETUP_LOG" | tail -n 40 >&2
        exit 1
    fi
}

# Hash of everything that decides what set-up produces.
inputs_hash() {
    (
        cd "$ROOT"
        {
            echo "root=$ROOT python=$(readlink -f "$VENV/bin/python" 2>/dev/null || true)"
            sha256sum requirements.txt setup.py setup.cfg package.xml run.sh \
                tools/fix_cmake_includes.py resource/gcn_match_ros 2>&1
            find msg_defs -type f -print0 | LC_ALL=C sort -z | xargs -0 sha256sum
        } | sha256sum | cut -d' ' -f1
    )
}

up_to_date() {
    [[ -x "$VENV/bin/python" && -f "$STAMP" ]] || return 1
    [[ -d "$VENV/lib/python3.11/site-packages/gcn_match_msgs" ]] || return 1
    [[ "$(cat "$STAMP")" == "$(inputs_hash)" ]]
}

build_msgs() {
    local args=(-S "$ROOT/msg_defs" -B "$MSG_BUILD"
        -DCMAKE_INSTALL_PREFIX="$VENV"
        -DPython3_EXECUTABLE="$VENV/bin/python"
        -DBUILD_TESTING=OFF
        -DCMAKE_BUILD_TYPE=Release)
    # A build dir configured for another source/prefix (moved clone, new venv) is
    # rejected by CMake: start it afresh then.
    if ! cmake "${args[@]}"; then
        echo "--- reconfiguring from scratch" 
        rm -rf "$MSG_BUILD"
        cmake "${args[@]}"
    fi
    cmake --build "$MSG_BUILD" -j "$(nproc 2>/dev/null || echo 2)"
    cmake --install "$MSG_BUILD"
}

check_env() {
    "$VENV/bin/python" - <<'EOF'
import array
import numpy as np
import torch, cv2, scipy, numba, threadpoolctl, rosbags, rclpy  # noqa: F401
from rclpy.serialization import serialize_message, deserialize_message
from gcn_match_msgs.msg import Keypoints, MatchWindow
import gcn_match_ros  # noqa: F401
m = Keypoints(count=1, keypoints=array.array('f', np.ones(2, np.float32).tobytes()))
assert list(deserialize_message(serialize_message(m), Keypoints).keypoints) == [1.0, 1.0]
deserialize_message(serialize_message(MatchWindow()), MatchWindow)
if torch.version.cuda is not None:
    print(f"warning: torch {torch.__version__} is a CUDA build (expected the CPU wheel)")
print(f"torch {torch.__version__}, numpy {np.__version__}, opencv {cv2.__version__}")
EOF
}

do_setup() {
    if up_to_date; then
        log "up to date"
        return 0
    fi
    command -v "$PYTHON" >/dev/null 2>&1 || [[ -x "$VENV/bin/python" ]] ||
        die "$PYTHON not found (set PYTHON=/path/to/python3.11)"
    command -v cmake >/dev/null 2>&1 || die "cmake not found (needed to build msg_defs/)"
    command -v c++ >/dev/null 2>&1 || command -v g++ >/dev/null 2>&1 ||
        die "no C++ compiler found (needed to build msg_defs/)"
    mkdir -p "$ROOT/build"
    : >"$SETUP_LOG"

    # Serialise concurrent set-ups (several shells/CI jobs sharing one .venv).
    exec 9>"$ROOT/build/.setup.lock"
    flock 9
    if up_to_date; then
        log "up to date (set up by a concurrent run)"
        exec 9>&-
        return 0
    fi

    local t0=$SECONDS
    if [[ ! -x "$VENV/bin/python" ]]; then
        step "creating .venv with $PYTHON" "$PYTHON" -m venv "$VENV"
    fi
    local pyver
    pyver="$("$VENV/bin/python" -c 'import sys; print("%d.%d" % sys.version_info[:2])')"
    [[ "$pyver" == "3.11" ]] || die ".venv uses Python $pyver; 3.11 is required (remove .venv, set PYTHON)"

    # torch: take the CPU build, never PyPI's default CUDA build.
    local torch_src=()
    if compgen -G "$TORCH_WHEEL_DIR/torch-${TORCH_VERSION}+cpu-cp311-*.whl" >/dev/null; then
        torch_src=(--find-links "$TORCH_WHEEL_DIR")
    else
        torch_src=(--extra-index-url https://download.pytorch.org/whl/cpu)
    fi
    step "installing requirements.txt (torch ${TORCH_VERSION}+cpu)" \
        "$VENV/bin/python" -m pip install -q -r "$ROOT/requirements.txt" \
        "torch==${TORCH_VERSION}+cpu" "${torch_src[@]}"

    step "fixing Python/numpy include paths in the ROS cmake files" \
        "$VENV/bin/python" "$ROOT/tools/fix_cmake_includes.py" "$VENV"

    (
        export VIRTUAL_ENV="$VENV" PATH="$VENV/bin:$PATH"
        export AMENT_PREFIX_PATH="$VENV" CMAKE_PREFIX_PATH="$VENV"
        step "building msg_defs/ (gcn_match_msgs) into .venv" build_msgs
    )

    step "installing gcn_match_ros (editable)" \
        "$VENV/bin/python" -m pip install -q --no-deps --no-build-isolation -e "$ROOT"

    step "checking the environment" check_env
    inputs_hash >"$STAMP"
    exec 9>&-
    log "done in $((SECONDS - t0)) s ($(tail -n 1 "$SETUP_LOG"))"
}

ros_env() {
    # No ROS traffic may leave this machine.
    export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
    unset ROS_LOCALHOST_ONLY || true
    export VIRTUAL_ENV="$VENV"
    export PATH="$VENV/bin:$PATH"
    export AMENT_PREFIX_PATH="$VENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
    export CMAKE_PREFIX_PATH="$VENV${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}"
    export PYTHONUNBUFFERED=1
}

cmd="${1:-}"
case "$cmd" in
    ""|-h|--help|help)
        usage
        [[ -n "$cmd" ]] || exit 2
        exit 0
        ;;
    setup)
        shift
        do_setup
        ;;
    test)
        shift
        do_setup
        ros_env
        export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$(( RANDOM % 100 + 1 ))}"
        tmp_log=""
        if [[ -z "${ROS_LOG_DIR:-}" ]]; then
            tmp_log="$(mktemp -d "${TMPDIR:-/tmp}/gcn_match_ros-roslog.XXXXXX")"
            export ROS_LOG_DIR="$tmp_log"
        fi
        cd "$ROOT"
        echo "[test] ROS_DOMAIN_ID=$ROS_DOMAIN_ID ROS_LOG_DIR=$ROS_LOG_DIR"
        rc=0
        # Default to the whole suite unless a test path/node id was given.
        targets=(test/)
        for a in "$@"; do
            if [[ "$a" != -* && ( -e "${a%%::*}" ) ]]; then targets=(); break; fi
        done
        "$VENV/bin/python" -m pytest "${targets[@]}" -q "$@" || rc=$?
        [[ -z "$tmp_log" ]] || rm -rf "$tmp_log"
        exit "$rc"
        ;;
    *)
        shift
        do_setup
        ros_env
        export ROS_LOG_DIR="${ROS_LOG_DIR:-$ROOT/log/ros}"
        mkdir -p "$ROS_LOG_DIR"
        if [[ "$cmd" == demo ]]; then
            exec "$VENV/bin/python" -m gcn_match_ros.ros.demo "$@"
        fi
        exec "$cmd" "$@"
        ;;
esac
