"""Shared test set-up: ROS isolation (localhost discovery, a domain id per run), data fixtures."""

from __future__ import annotations

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


def load_script(name: str) -> ModuleType:
    """``scripts/<name>.py`` imported as module ``name`` (scripts/ is no package; its dataclasses look it up)."""
    spec = importlib.util.spec_from_file_location(name, REPO / "scripts" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


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
