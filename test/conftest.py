"""Shared test set-up: ROS isolation (localhost discovery, a domain id per run), data fixtures."""

from __future__ import annotations

import fcntl
import importlib.util
import os
import random
import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import pytest

# ROS hygiene before anything imports rclpy: loopback-only discovery, and a domain id of this run's
# own so that two test runs on one machine never hear each other (xdist workers get their own).
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
# Passive OpenMP waits, before torch loads (roigsf_ros/__init__.py sets the same default).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
if "ROIGSF_TEST_DOMAIN_ID" not in os.environ:
    os.environ["ROIGSF_TEST_DOMAIN_ID"] = str(random.SystemRandom().randrange(1, 100))
_worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
os.environ["ROS_DOMAIN_ID"] = str(int(os.environ["ROIGSF_TEST_DOMAIN_ID"]) + int(_worker.lstrip("gw") or 0))

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("ROIGSF_SHARED_DATA", REPO.parent / "shared" / "data"))
OFFICE0 = SHARED_DATA / "replica_office0"
SHM = Path("/dev/shm")


def load_script(name: str) -> ModuleType:
    """``scripts/<name>.py`` imported as module ``name`` (scripts/ is no package; its dataclasses look it up)."""
    spec = importlib.util.spec_from_file_location(name, REPO / "scripts" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def fastdds_files() -> set[str]:
    """Names of the Fast DDS shared-memory files in /dev/shm (segments, their locks and port files)."""
    return {p.name for p in SHM.glob("fastrtps_*")} if SHM.is_dir() else set()


def _mapped_shm() -> set[str]:
    """Names of the /dev/shm files some live process has mapped (its /proc/<pid>/maps; unreadable ones skipped)."""
    names: set[str] = set()
    for maps in Path("/proc").glob("[0-9]*/maps"):
        try:
            text = maps.read_text()
        except OSError:
            continue
        names.update(line.rsplit("/", 1)[-1] for line in text.splitlines() if f" {SHM}/" in line)
    return names


def remove_zombie_shm(before: set[str]) -> None:
    """Remove Fast DDS files created since ``before`` whose owners are gone.

    A live participant holds an exclusive flock on its segment's ``_el`` file; only unlocked ones
    (left by a SIGKILLed process) are removed, so other processes' segments are never touched. Port files
    (``fastrtps_port<N>`` and their ``sem.fastrtps_port<N>_mutex``) have no such lock: they are removed when no
    live process maps them (Fast DDS removes them itself on a clean exit; ``fastdds shm clean`` leaves them).
    """
    new = fastdds_files() - before
    if any(name.startswith("fastrtps_port") for name in new):
        mapped = _mapped_shm()
        for name in sorted(n for n in new if n.startswith("fastrtps_port")):
            sem = f"sem.{name}_mutex"
            if name not in mapped and sem not in mapped:
                (SHM / name).unlink(missing_ok=True)
                (SHM / sem).unlink(missing_ok=True)
    for name in sorted(new):
        if not name.endswith("_el") or name.startswith("fastrtps_port"):
            continue
        lock = SHM / name
        try:
            fd = os.open(lock, os.O_RDWR)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            continue  # alive
        try:
            (SHM / name[: -len("_el")]).unlink(missing_ok=True)
            lock.unlink(missing_ok=True)
        finally:
            os.close(fd)


_SHM_AT_START: set[str] = set()


def pytest_sessionstart(session: pytest.Session) -> None:
    """Note the Fast DDS files there before the run (the controller's, with xdist), for the clean-up at its end."""
    _SHM_AT_START.update(fastdds_files())


def pytest_sessionfinish(session: pytest.Session) -> None:
    """Once every test has run (on the controller, with xdist, after all workers): remove the Fast DDS files the run
    left whose owners are gone. test_system.py cleans after its own module, but a port file a test on the other worker
    made meanwhile was still mapped then.
    """
    if not hasattr(session.config, "workerinput"):
        remove_zombie_shm(_SHM_AT_START)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Tests marked ``slow`` first (a stable sort): with ``scripts/test.sh``'s two xdist workers, which take whole
    files in collection order (``--no-loadscope-reorder``), the two longest files (the cold-cache demo, the system
    tests) start at once instead of one of them running alone at the end.
    """
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    """After a run that included the bad-input corpus (test_bad_input_corpus.py): cases tried and survived."""
    reports = [
        r
        for key in ("passed", "failed", "error")
        for r in terminalreporter.stats.get(key, [])
        if getattr(r, "when", "") == "call" and "test_bad_input_corpus.py::" in getattr(r, "nodeid", "")
    ]
    if reports:
        survived = sum(r.passed for r in reports)
        terminalreporter.write_line(f"bad-input corpus: {len(reports)} cases tried, {survived} survived")


@pytest.fixture(scope="session")
def office0() -> Path:
    """The shared real Replica office0 sample (mesh, 2000 poses, 4 frames); skips when absent."""
    if not (OFFICE0 / "office0" / "traj.txt").is_file() or not (OFFICE0 / "office0_mesh.ply").is_file():
        pytest.skip(f"Replica office0 sample not found at {OFFICE0} (set ROIGSF_SHARED_DATA; not redistributable)")
    return OFFICE0


@pytest.fixture
def ros_context() -> Iterator[object]:
    """A fresh rclpy Context on this run's domain, shut down after the test."""
    rclpy = pytest.importorskip("rclpy")
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(os.environ["ROS_DOMAIN_ID"]))
    try:
        yield ctx
    finally:
        ctx.try_shutdown()


@pytest.fixture(scope="module")
def one_torch_thread() -> Iterator[None]:
    """One torch thread for a module (``pytestmark = pytest.mark.usefixtures("one_torch_thread")``).

    On a shared 2-core machine OpenMP's spinning threads can make small passes 10-50x slower.
    """
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
