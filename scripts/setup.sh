#!/usr/bin/env bash
# Idempotent set-up of a fresh machine: Debian packages, .venv with pinned packages, this package.
# Sourced by scripts/demo.sh and scripts/test.sh (and by a user's shell: `source scripts/setup.sh`), or run; safe to
# run again (skips what is already done). After it: $VENV is the virtualenv and ROS variables are exported for the
# shell that sourced it. The installing steps run in a child bash with `set -euo pipefail`, so their options, traps
# and exits stay there: sourced into an interactive shell, `set -e` used to stay on and close the terminal at the
# first failing command. A failed set-up returns its exit status to the shell that sourced it and exports nothing.

if [ "${ROIGSF_SETUP_CHILD:-}" != 1 ]; then
    ROIGSF_SETUP_CHILD=1 bash "${BASH_SOURCE[0]}" && _roigsf_setup_rc=0 || _roigsf_setup_rc=$?
    if [ "$_roigsf_setup_rc" -eq 0 ]; then
        unset _roigsf_setup_rc
        VENV="${ROIGSF_VENV:-$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)/.venv}"
        # The environment for ROS: ament index in the venv, loopback-only discovery.
        export VIRTUAL_ENV="$VENV"
        export PATH="$VENV/bin:$PATH"
        export AMENT_PREFIX_PATH="$VENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
        export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
        # glibc allocator settings that made torch on this CPU 1.3-2x faster and less noisy (page faults).
        export MALLOC_MMAP_MAX_="${MALLOC_MMAP_MAX_:-0}"
        export MALLOC_TRIM_THRESHOLD_="${MALLOC_TRIM_THRESHOLD_:-100000000000}"
        # torch's spinning OpenMP workers starve the renderer's numba threads on 2 cores.
        export OMP_WAIT_POLICY="${OMP_WAIT_POLICY:-PASSIVE}"
        return 0 2>/dev/null || exit 0
    fi
    printf '[setup] error: set-up did not finish (exit %s; the lines above say why); nothing was exported\n' \
        "$_roigsf_setup_rc" >&2
    return "$_roigsf_setup_rc" 2>/dev/null || exit "$_roigsf_setup_rc"
fi

# The installing steps (the child bash).
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${ROIGSF_VENV:-$REPO/.venv}"
log() { printf '[setup] %s\n' "$*" >&2; }

# Background steps (the interface build, the kernels' compile) and how set-up stops them. A background job of a
# non-interactive shell ignores Ctrl-C, and set-up exiting on a failed step does not stop it: without this, a failed
# pip step or a Ctrl-C left cmake and the compilers (or numba) running. While background steps run, INT and TERM stop
# every process they started and end set-up, as does any step that fails.
SETUP_BG_PIDS=()
setup_tree() {  # a process and all its descendants, parents first
    local child
    echo "$1"
    for child in $(pgrep -P "$1" 2>/dev/null || true); do setup_tree "$child"; done
}
setup_stop_background() {  # freeze the trees (no new children), then end them
    local pid tree=()
    for pid in "${SETUP_BG_PIDS[@]}"; do mapfile -t -O "${#tree[@]}" tree < <(setup_tree "$pid"); done
    [ "${#tree[@]}" -gt 0 ] || return 0
    kill -STOP "${tree[@]}" 2>/dev/null || true
    kill -TERM "${tree[@]}" 2>/dev/null || true
    kill -CONT "${tree[@]}" 2>/dev/null || true
    for pid in "${SETUP_BG_PIDS[@]}"; do wait "$pid" 2>/dev/null || true; done
    SETUP_BG_PIDS=()
}
setup_fail() {  # stop the background steps, say why, exit
    setup_stop_background
    log "error: $1"
    exit "${2:-1}"
}
trap 'setup_fail "interrupted" 130' INT
trap 'setup_fail "terminated" 143' TERM

# 1. Debian packages: open3d needs libusb-1.0 at import time.
if ! ldconfig -p 2>/dev/null | grep 'libusb-1.0.so.0' >/dev/null; then  # no -q: an early exit SIGPIPEs ldconfig under pipefail
    log "installing Debian package libusb-1.0-0 (open3d needs it)"
    SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null
fi

# 2. Python 3.11: the ROS 2 Jazzy wheels on PyPI are built for CPython 3.11 only.
PY="${ROIGSF_PYTHON:-}"
if [ -z "$PY" ]; then
    for cand in python3.11 python3; do
        if command -v "$cand" >/dev/null && "$cand" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
            PY="$cand"; break
        fi
    done
fi
[ -n "$PY" ] || { log "error: Python 3.11 is required (ROS 2 Jazzy wheels are cp311); set ROIGSF_PYTHON"; exit 1; }

if [ ! -x "$VENV/bin/python" ]; then
    log "creating virtualenv $VENV"
    "$PY" -m venv "$VENV"
fi

# pip's warning about each index location of this machine's pip config that does not exist (one per package looked up:
# 326 lines on a fresh set-up here) buried the set-up's own lines: counted in one line; anything else pip says is shown.
PIP_IGNORED='is ignored: it is neither a file nor a directory'
pip_install() {
    local out rc=0 n
    out="$("$VENV/bin/python" -m pip install "$@" 2>&1)" || rc=$?
    printf '%s\n' "$out" | { grep -v -e "$PIP_IGNORED" -e '^$' >&2 || true; }
    n="$(printf '%s\n' "$out" | grep -c -e "$PIP_IGNORED" || true)"
    [ "$n" = 0 ] || log "pip: $n warning(s) hidden (index locations in this machine's pip config that do not exist)"
    return "$rc"
}

# 3. Pinned packages, reinstalled only when requirements.txt changes: first all but the heavy wheels (torch, open3d,
#    ...), which the interface build of step 4 does not need; then, while the interfaces build, the heavy ones. (The
#    build used to wait for every wheel and then compete with the kernel compile of step 6 for the 2 cores.)
HEAVY='torch|open3d|opencv-python-headless|scikit-image|matplotlib|scipy|numba|llvmlite'
REQ_HASH="$(sha256sum "$REPO/requirements.txt" | cut -d' ' -f1)"
STAMP="$VENV/.roigsf-requirements.sha256"
REQ_HEAVY=0
if [ "$(cat "$STAMP" 2>/dev/null || true)" != "$REQ_HASH" ]; then
    log "installing pinned packages (requirements.txt; the heavy wheels while the interfaces build)"
    pip_install -q --upgrade pip
    grep -v -E "^($HEAVY)==" "$REPO/requirements.txt" > "$VENV/.roigsf-requirements-light.txt"
    pip_install -q -r "$VENV/.roigsf-requirements-light.txt"
    REQ_HEAVY=1
fi

# 4. The interface packages (ament_cmake: roigsf_interfaces, and tf2_msgs if missing), rebuilt when its sources or the
#    pinned packages change; in the background, while pip installs the heavy wheels (step 3) and the kernels compile
#    (step 6): it needs none of them. Set-up waits for it at its end.
IFACE_HASH="$(cat "$REPO/requirements.txt" "$REPO"/roigsf_interfaces/{CMakeLists.txt,package.xml} \
    "$REPO"/roigsf_interfaces/srv/*.srv "$REPO"/vendor/tf2_msgs/{CMakeLists.txt,package.xml,msg/TFMessage.msg} \
    "$REPO/scripts/build_interfaces.sh" | sha256sum | cut -d' ' -f1)"
IFACE_STAMP="$VENV/.roigsf-interfaces.sha256"
IFACE_PID=""
if [ "$(cat "$IFACE_STAMP" 2>/dev/null || true)" != "$IFACE_HASH" ]; then
    log "building roigsf_interfaces (and tf2_msgs if missing) into $VENV"
    bash "$REPO/scripts/build_interfaces.sh" "$VENV" &
    IFACE_PID="$!"
    SETUP_BG_PIDS+=("$IFACE_PID")
fi
if [ "$REQ_HEAVY" = 1 ]; then
    pip_install -q -r "$REPO/requirements.txt" \
        || setup_fail "pip could not install $REPO/requirements.txt (exit $?)"
    echo "$REQ_HASH" > "$STAMP"
fi

# 5. This package (not editable: pip -e drops the ament marker and config data_files).
log "installing roigsf_ros into $VENV"
"$VENV/bin/python" -m pip install -q --no-deps --no-build-isolation --force-reinstall "$REPO" 2>&1 \
    | { grep -v -e 'DEPRECATION' -e "$PIP_IGNORED" -e '^$' >&2 || true; } || setup_fail "pip could not install roigsf_ros from $REPO"
rm -rf "$REPO/build" "$REPO"/*.egg-info

# 6. The numba kernels (rasteriser, Fisher, ROI), compiled once into numba's disk cache beside the installed
#    modules: cold, they take 80-170 s, which the planner's first requests on a fresh machine used to pay (the
#    selector's fallback decided those windows). Redone when the package's sources or the pinned packages
#    change, or when the cache files are gone; run outside the repo so the installed copy is the one compiled, split
#    over every CPU (--jobs, by the package's kernel signature list: 147-166 s on one process, 80-98 s on two, 2 cores).
#    Then the checkout's own copy (which the tests and `python -m roigsf_ros...` in the repo import) is warmed up, after
#    each compile and always with ROIGSF_WARM_CHECKOUT=1 (scripts/test.sh): numba names a cache by module, function and
#    line and stamps it with the source's hash, so the installed copy's compiled kernels are copied into the checkout
#    (--seed-from; byte-identical modules only) and load in about a second. (The two copies used to compile side by
#    side, one process each: about a minute longer on 2 cores.) In the background; set-up waits at its end.
KERNEL_HASH="$(cat "$REPO/requirements.txt" "$REPO"/roigsf_ros/*/*.py "$REPO/roigsf_ros/nbv/kernel_signatures.json" \
    | sha256sum | cut -d" " -f1)"
KERNEL_STAMP="$VENV/.roigsf-kernels.sha256"
WARM_PID=""
WARM_INSTALLED=0
WARM_CHECKOUT="${ROIGSF_WARM_CHECKOUT:-0}"
INSTALLED_PKG="$(compgen -G "$VENV/lib/python3*/site-packages/roigsf_ros" | head -n 1 || true)"
[ -n "$INSTALLED_PKG" ] || setup_fail "roigsf_ros is not in $VENV's site-packages after step 5"
if [ "$(cat "$KERNEL_STAMP" 2>/dev/null || true)" != "$KERNEL_HASH" ] \
    || ! compgen -G "$INSTALLED_PKG/render/__pycache__/*.nbi" >/dev/null; then
    WARM_INSTALLED=1
fi
warm_kernels() {  # the installed copy (when its cache is stale), then the checkout seeded from it (when asked)
    if [ "$WARM_INSTALLED" = 1 ]; then
        (cd / && "$VENV/bin/python" -m roigsf_ros.nbv.warmup --jobs "$(nproc)" | sed 's/^/[setup] /' >&2)
    fi
    if [ "$WARM_CHECKOUT$WARM_INSTALLED" != 00 ]; then
        (cd "$REPO" && "$VENV/bin/python" -m roigsf_ros.nbv.warmup --jobs 1 --seed-from "$INSTALLED_PKG" \
            | sed 's/^/[checkout] /' >&2)
    fi
}
if [ "$WARM_INSTALLED$WARM_CHECKOUT" != 00 ]; then
    [ "$WARM_INSTALLED" = 0 ] || log "compiling the numba kernels (once; cached on disk; processes: $(nproc))"
    warm_kernels &
    WARM_PID="$!"
    SETUP_BG_PIDS+=("$WARM_PID")
fi

# The background work of steps 4 and 6.
IFACE_RC=0
[ -z "$IFACE_PID" ] || wait "$IFACE_PID" || IFACE_RC=$?
[ "$IFACE_RC" -eq 0 ] || setup_fail "building the interfaces failed (exit $IFACE_RC)" "$IFACE_RC"
WARM_RC=0
[ -z "$WARM_PID" ] || wait "$WARM_PID" || WARM_RC=$?
SETUP_BG_PIDS=()
[ -z "$IFACE_PID" ] || echo "$IFACE_HASH" > "$IFACE_STAMP"
[ "$WARM_RC" -eq 0 ] || { log "error: compiling the numba kernels failed (exit $WARM_RC)"; exit "$WARM_RC"; }
[ "$WARM_INSTALLED" -eq 0 ] || echo "$KERNEL_HASH" > "$KERNEL_STAMP"
