"""``roigsf demo`` (the main job) ends without a traceback: no node is destroyed under a spinning executor."""

from __future__ import annotations

import json
import re
import threading
from pathlib import Path

import pytest

pytest.importorskip("rclpy")
pytest.importorskip("roigsf_interfaces")

from rclpy.node import Node

from roigsf_ros.data import bags
from roigsf_ros.data.replica import ReplicaSequence
from roigsf_ros.perf.io import make_synthetic_replica

pytestmark = pytest.mark.ros
REPO = Path(__file__).resolve().parents[1]
TRACEBACK = re.compile(r"Traceback|never retrieved|InvalidHandle")
"""What the demo's output may not show: a traceback (the executor thread's InvalidHandle), a lost exception."""


def _bag(root: Path, frames: int, width: int, height: int, seed: int) -> Path:
    make_synthetic_replica(root / "scene", width, height, frames, seed=seed)
    bags.write_bag(ReplicaSequence(root / "scene"), root / "bag", progress=False)  # 10 Hz
    return root / "bag"


def test_demo_destroys_no_node_while_the_executor_spins(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    """Every node (the player included) is destroyed after the executor thread stopped.

    Before: the demo destroyed the bag player while ``active_mapping``'s executor still spun it, and the
    executor thread sometimes failed on the player's handles ("InvalidHandle: cannot use Destroyable
    because destruction was requested", a traceback at the end of the demo).
    """
    from roigsf_ros.cli import main

    bag = _bag(tmp_path, 4, 32, 24, seed=3)
    destroyed_while_spinning: list[str] = []
    destroy = Node.destroy_node

    def checked_destroy(self: Node) -> None:
        if any(t.name == "active_mapping_executor" and t.is_alive() for t in threading.enumerate()):
            destroyed_while_spinning.append(self.get_name())
        destroy(self)

    monkeypatch.setattr(Node, "destroy_node", checked_destroy)
    run = tmp_path / "run"
    args = ["demo", "--bag", str(bag), "--out", str(run), "--rate", "0", "--gt-mesh", "", "--no-progress"]
    assert main([*args, "--policy", "every-n", "--final-iters", "5"]) == 0
    assert destroyed_while_spinning == []
    out = capfd.readouterr()
    assert not TRACEBACK.search(out.out + out.err), out.err
    assert json.loads((run / "metrics.json").read_text())["n_frames"] == 4
