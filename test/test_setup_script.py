"""scripts/setup.sh's failure paths, run on a scratch copy of the repository with a fake pip and interface build.

Set-up builds the interfaces in the background while pip installs the heavy wheels. These tests check that a failed
pip step or a Ctrl-C stops that build and everything under it, and that sourcing set-up never changes the caller's
shell options (`set -e` left on in an interactive shell closed the terminal at its next failing command). No pip, no
compiler: the scratch repository's python and build script are small shell scripts that record what they were asked.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

FAKE_PYTHON = """#!/usr/bin/env bash
# Stands in for the venv's python: records the call and its folder; "pip install -r <repo>/requirements.txt" (the heavy
# wheels) waits for the fake build's child to start, then fails (FAKE_HEAVY=fail) or hangs (FAKE_HEAVY=hang); the
# package's install makes its folder in site-packages.
echo "$PWD: $*" >> "$FAKE_MARK/python.log"
case "$*" in
    *"-r $FAKE_REPO/requirements.txt"*)
        for _ in $(seq 100); do [ -s "$FAKE_MARK/build_child.pid" ] && break; sleep 0.1; done
        case "${FAKE_HEAVY:-ok}" in fail) exit 3 ;; hang) sleep 60 ;; esac ;;
    *"--force-reinstall $FAKE_REPO"*) mkdir -p "$FAKE_REPO/.venv/lib/python3.11/site-packages/roigsf_ros" ;;
esac
exit 0
"""

FAKE_BUILD = """#!/usr/bin/env bash
# Stands in for scripts/build_interfaces.sh: a long build with a child process (the compilers under cmake).
echo "$$" > "$FAKE_MARK/build.pid"
sleep "${FAKE_BUILD_S:-120}" &
echo "$!" > "$FAKE_MARK/build_child.pid"
wait
"""


def _libusb_present() -> bool:
    """Step 1 of set-up installs libusb with apt when it is missing; the scratch runs must not."""
    out = subprocess.run(["ldconfig", "-p"], capture_output=True, text=True, check=False).stdout
    return "libusb-1.0.so.0" in out


pytestmark = pytest.mark.skipif(
    shutil.which("pgrep") is None or not _libusb_present(),
    reason="needs pgrep and libusb-1.0 (installed by the real set-up) so that the scratch set-up runs no apt-get",
)


def _write(path: Path, text: str, mode: int = 0o644) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    path.chmod(mode)


@pytest.fixture
def scratch(tmp_path: Path) -> Iterator[dict[str, str]]:
    """A repository with set-up's real script and the files its hashes read, a fake venv; yields the environment, and
    afterwards kills whatever of the fake build is still running (on a failed test, nothing is left behind)."""
    repo, mark, venv = tmp_path / "repo", tmp_path / "mark", tmp_path / "repo" / ".venv"
    shutil.copy(REPO / "scripts" / "setup.sh", _mkdir(repo / "scripts") / "setup.sh")
    _write(repo / "scripts" / "build_interfaces.sh", FAKE_BUILD, 0o755)
    _write(repo / "requirements.txt", "torch==2.13.0\nrosbags==0.11.9\n")
    for name in ("roigsf_interfaces/CMakeLists.txt", "roigsf_interfaces/package.xml", "roigsf_interfaces/srv/A.srv",
                 "vendor/tf2_msgs/CMakeLists.txt", "vendor/tf2_msgs/package.xml", "vendor/tf2_msgs/msg/TFMessage.msg",
                 "roigsf_ros/nbv/kernel_signatures.json", "roigsf_ros/nbv/a.py"):  # fmt: skip
        _write(repo / name, name)
    _write(venv / "bin" / "python", FAKE_PYTHON, 0o755)
    mark.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith(("ROIGSF_", "FAKE_", "VIRTUAL_ENV"))}
    env.update(FAKE_REPO=str(repo), FAKE_MARK=str(mark), ROIGSF_PYTHON="/bin/true", ROIGSF_WARM_CHECKOUT="0")
    yield env
    for name in ("build.pid", "build_child.pid"):
        try:
            pid = int((mark / name).read_text())
        except (OSError, ValueError):
            continue
        if _alive(pid):
            os.kill(pid, signal.SIGKILL)


def _mkdir(path: Path) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    return path


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie waiting for its reaper counts as gone)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"


def _build_pids(env: dict[str, str]) -> list[int]:
    mark = Path(env["FAKE_MARK"])
    return [int((mark / name).read_text()) for name in ("build.pid", "build_child.pid")]


def _assert_build_stopped(env: dict[str, str]) -> None:
    pids = _build_pids(env)
    deadline = time.monotonic() + 5.0
    while any(_alive(p) for p in pids) and time.monotonic() < deadline:
        time.sleep(0.05)
    left = [p for p in pids if _alive(p)]
    assert not left, f"set-up exited and left its interface build running: {left}"


def test_a_failed_heavy_pip_step_stops_the_interface_build(scratch: dict[str, str]) -> None:
    """pip failing while the interfaces build: set-up exits non-zero, says which step, and stops the whole build."""
    env = {**scratch, "FAKE_HEAVY": "fail"}
    proc = subprocess.run(
        ["bash", str(Path(env["FAKE_REPO"]) / "scripts" / "setup.sh")],
        env=env, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert proc.returncode != 0
    assert "pip could not install" in proc.stderr and "requirements.txt" in proc.stderr, proc.stderr
    _assert_build_stopped(env)
    assert not (Path(env["FAKE_REPO"]) / ".venv" / ".roigsf-requirements.sha256").exists()  # redone next time


def test_ctrl_c_during_set_up_stops_the_interface_build(scratch: dict[str, str]) -> None:
    """SIGINT to set-up's process group (Ctrl-C in a terminal) while pip runs and the interfaces build: exit 130,
    nothing of the build left (a background job of a script ignores SIGINT, so it used to go on).
    """
    env = {**scratch, "FAKE_HEAVY": "hang"}
    # bash cannot trap a signal ignored when it starts, and a test run started in the background (a job of a script,
    # nohup ...) inherits SIGINT ignored: start set-up with SIGINT at its default, as a terminal's foreground job has it
    reset_sigint = (
        "import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_DFL); os.execvp('bash', sys.argv[1:])"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", reset_sigint, "bash", str(Path(env["FAKE_REPO"]) / "scripts" / "setup.sh")],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
    )  # fmt: skip
    try:
        child = Path(env["FAKE_MARK"]) / "build_child.pid"
        deadline = time.monotonic() + 20.0
        while not child.exists() or not child.read_text().strip():
            assert time.monotonic() < deadline and proc.poll() is None, "the fake build never started"
            time.sleep(0.05)
        time.sleep(0.3)  # the fake pip is now waiting too
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 130, err
    assert "interrupted" in err
    _assert_build_stopped(env)


@pytest.mark.parametrize("outcome", ["ok", "fail"])
def test_sourcing_set_up_leaves_the_callers_shell_options_alone(scratch: dict[str, str], outcome: str) -> None:
    """Sourced: the caller's options stay as they were (no errexit, nounset or pipefail turned on), a failed set-up
    returns its status to the caller, which goes on, and only a finished one exports the venv.
    """
    env = {**scratch, "FAKE_HEAVY": outcome, "FAKE_BUILD_S": "0"}
    script = (
        f"source {Path(env['FAKE_REPO']) / 'scripts' / 'setup.sh'}; rc=$?\n"
        'false; echo "after false: options $-, rc $rc, VIRTUAL_ENV=${VIRTUAL_ENV:-unset}"\n'
        "set -o | grep -E '^(errexit|nounset|pipefail) ' | tr -s ' \\t' ' '\n"
    )
    proc = subprocess.run(["bash", "-c", script], env=env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert lines[0].startswith("after false:"), proc.stdout  # errexit would have ended the shell at `false`
    assert lines[1:] == ["errexit off", "nounset off", "pipefail off"], proc.stdout
    if outcome == "ok":
        assert lines[0].endswith(f"rc 0, VIRTUAL_ENV={Path(env['FAKE_REPO']) / '.venv'}"), proc.stdout
    else:
        assert lines[0].endswith("rc 1, VIRTUAL_ENV=unset"), proc.stdout
        assert "nothing was exported" in proc.stderr


def test_kernels_compile_once_and_the_checkout_is_seeded_from_them(scratch: dict[str, str]) -> None:
    """The installed copy compiles the kernels on every CPU; only then does the checkout's warm-up run, seeded with
    them (``--seed-from`` the installed package), after every compile (``python -m roigsf_ros...`` in the repo imports
    the checkout) and, with a warm cache, for the tests only. The two copies used to compile side by side, one process
    each, about a minute longer on 2 cores."""
    repo, mark = Path(scratch["FAKE_REPO"]), Path(scratch["FAKE_MARK"])
    installed = repo / ".venv" / "lib" / "python3.11" / "site-packages" / "roigsf_ros"
    cpus = subprocess.run(["nproc"], capture_output=True, text=True, check=True).stdout.strip()
    compile_all = f"/: -m roigsf_ros.nbv.warmup --jobs {cpus}"
    seed = f"{repo}: -m roigsf_ros.nbv.warmup --jobs 1 --seed-from {installed}"

    def warmups(warm_checkout: str) -> list[str]:
        (mark / "python.log").unlink(missing_ok=True)
        env = {**scratch, "FAKE_BUILD_S": "0", "ROIGSF_WARM_CHECKOUT": warm_checkout}
        proc = subprocess.run(["bash", str(repo / "scripts" / "setup.sh")], env=env, capture_output=True, text=True,
                              timeout=60)  # fmt: skip
        assert proc.returncode == 0, proc.stderr
        return [line for line in (mark / "python.log").read_text().splitlines() if "warmup" in line]

    assert warmups("1") == [compile_all, seed]
    assert warmups("0") == [compile_all, seed]  # no cache files yet: compiled again, and the checkout seeded
    _write(installed / "render" / "__pycache__" / "rasterize._k_forward-1.py311.nbi", "")  # the cache is there now
    assert warmups("0") == []
    assert warmups("1") == [seed]
