"""``roigsf ros`` without nodes: the request built from a pose file, the answer's table, and the errors that need no
graph (bad names, bad files, nothing running). Against running node processes: test_system.py."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("roigsf_interfaces.srv")

from roigsf_interfaces.srv import GetNextBestView
from roigsf_ros.cli import main
from roigsf_ros.cli.ros import candidates_request, directory_arg, nbv_answer, nbv_table, node_path
from roigsf_ros.core.camera import pose_from_position_quat
from roigsf_ros.core.errors import InputError
from roigsf_ros.data.replica import save_traj

pytestmark = pytest.mark.ros


def _poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        q = rng.normal(size=4)
        out.append(pose_from_position_quat(rng.normal(size=3), q / np.linalg.norm(q)))
    return np.asarray(out)


def test_node_names() -> None:
    assert node_path("mapper") == "/mapper" and node_path("/robot1/mapper/") == "/robot1/mapper"
    for bad in ("", "/", "map per"):
        with pytest.raises(InputError, match="NODE: not a node name"):
            node_path(bad)


def test_the_request_holds_the_file_poses_in_order(tmp_path: Path) -> None:
    poses = _poses(5)
    path = tmp_path / "cands.txt"
    save_traj(path, poses)
    req = candidates_request(path, "", 3, "fisherrf")
    assert req.top_k == 3 and req.mode == "fisherrf" and req.candidates.header.frame_id == ""
    assert req.candidates.header.stamp.sec == 0 and req.candidates.header.stamp.nanosec == 0  # never "stale"
    back = np.asarray(
        [
            pose_from_position_quat(
                np.array([p.position.x, p.position.y, p.position.z]),
                np.array([p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w]),
            )
            for p in req.candidates.poses
        ]
    )
    np.testing.assert_allclose(back, poses, atol=1e-6)
    with pytest.raises(InputError, match="--top-k"):
        candidates_request(path, "", -1, "")
    bad = tmp_path / "bad.txt"
    bad.write_text("1 2 3\n")
    with pytest.raises(InputError, match=r"bad\.txt"):
        candidates_request(bad, "", 0, "")


def test_the_answer_and_its_table_name_file_lines() -> None:
    res = GetNextBestView.Response(success=True, message="scored 3 candidates (roi-gsurfisher)", best_index=2)
    res.top_k_indices = [2, 0]
    res.fused_scores, res.fisher_scores, res.close_front_scores = [0.5, -1.0, 1.5], [10.0, 1.0, 30.0], [2.0, 1.0, 3.0]
    res.best_pose.header.frame_id = "map"
    res.best_pose.pose.orientation.w = 1.0
    answer = nbv_answer(res)
    assert answer["best_index"] == 2 and answer["best_pose"]["quaternion_xyzw"] == [0.0, 0.0, 0.0, 1.0]
    json.dumps(answer)  # JSON-ready
    rows = nbv_table(answer).splitlines()
    assert len(rows) == 3  # header + the top 2
    assert rows[1].split() == ["1", "3", "1.5", "30", "3"]  # rank 1 is line 3 of the file (index 2)
    assert rows[2].split() == ["2", "1", "0.5", "10", "2"]


def test_errors_without_nodes_name_what_was_not_found(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Nothing runs on a domain no test uses: each action says what it looked for, where, and exits 2."""
    save_traj(tmp_path / "c.txt", _poses(2))
    domain_before = os.environ["ROS_DOMAIN_ID"]
    domain = ["--domain-id", "232", "--wait", "0.5"]
    assert main(["ros", "status", "mapper", *domain]) == 2
    err = capsys.readouterr().err
    assert "/mapper/status: no publisher within 0.5 s" in err and "ROS_DOMAIN_ID=232" in err
    assert err.rstrip().endswith("? no node seen"), err
    assert main(["ros", "nbv", "--candidates", str(tmp_path / "c.txt"), *domain]) == 2
    assert "/nbv_planner/get_next_best_view: no such service within 0.5 s" in capsys.readouterr().err
    assert main(["ros", "save-map", str(tmp_path / "m"), "--mapper", "/robot1/mapper", *domain]) == 2
    assert "/robot1/mapper/save_map: no such service" in capsys.readouterr().err
    assert main(["ros", "finish", *domain]) == 2
    assert "/keyframe_selector/finish: no such service" in capsys.readouterr().err
    # Bad input is refused before any ROS work.
    assert main(["ros", "nbv", "--candidates", str(tmp_path / "none.txt"), *domain]) == 2
    assert "none.txt" in capsys.readouterr().err
    if Path("/proc/self").is_dir():  # a folder nothing can be created in, even as root: the output is named too
        assert main(["ros", "nbv", "--candidates", str(tmp_path / "c.txt"), "--out", "/proc/x/nbv.json", *domain]) == 2
        assert "/proc/x/nbv.json cannot be written there" in capsys.readouterr().err
    assert main(["ros", "status", "mapper", "--domain-id", "300"]) == 2
    assert "--domain-id: must be a ROS domain id in 0..232, got 300" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["ros", "status", "mapper", "--wait", "-1"])
    assert "--wait: must be in (0, 1e6) seconds" in capsys.readouterr().err
    assert not (tmp_path / "m").exists()
    assert os.environ["ROS_DOMAIN_ID"] == domain_before  # --domain-id is this command's, not the process's


def test_a_mistyped_node_name_lists_the_nodes_seen(ros_context: object, capsys: pytest.CaptureFixture[str]) -> None:
    """``roigsf ros status mappr`` waited its ``--wait`` and said only "is /mappr running?"; it now lists the nodes
    the graph holds, with the closest name."""
    from rclpy.node import Node

    node = Node("mapper", context=ros_context)
    try:
        assert main(["ros", "status", "mappr", "--wait", "5"]) == 2  # time for discovery on a loaded machine
        err = capsys.readouterr().err
        assert "/mappr/status: no publisher within 5 s" in err and "nodes seen: " in err, err
        assert "/mapper" in err.split("nodes seen: ", 1)[1] and "(did you mean /mapper?)" in err, err
        assert main(["ros", "finish", "--selector", "mappr", "--wait", "5"]) == 2
        assert "(did you mean /mapper?)" in capsys.readouterr().err
    finally:
        node.destroy_node()


def test_a_bad_domain_from_the_environment_is_named(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Before (session 61's walk): "abc" gave rcl's traceback, 999 Fast DDS's bare log line and /dev/shm files."""
    for value, problem in (("abc", "not an integer: 'abc'"), ("999", "must be a ROS domain id in 0..232, got 999")):
        monkeypatch.setenv("ROS_DOMAIN_ID", value)
        assert main(["ros", "status", "mapper", "--wait", "0.5"]) == 2
        assert f"roigsf ros: error: ROS_DOMAIN_ID: {problem}" in capsys.readouterr().err


def test_map_folders_are_sent_absolute_and_names_of_no_folder_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``save-map .`` in a saved map's folder replaced it: the absolute path slipped past the mapper's refusal of
    ``.``; ``'~/m'`` made a folder named ``~``; ``''`` named the working folder (session 61's walk)."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert directory_arg("maps/a") == str(tmp_path / "maps" / "a")  # the caller's folder, not the node's
    assert directory_arg("~/m") == str(tmp_path / "home" / "m")
    for bad in ("", " ", ".", "..", "maps/..", "/", "./"):
        with pytest.raises(InputError, match="names no folder of its own"):
            directory_arg(bad)
