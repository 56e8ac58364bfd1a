"""``roigsf demo`` (the main job): plans from its first window on a cold numba cache, and ends without a traceback."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("rclpy")
pytest.importorskip("roigsf_interfaces")

from rclpy.node import Node

from roigsf_ros.core.errors import InputError
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


@pytest.mark.slow
def test_demo_on_a_cold_numba_cache_plans_from_the_first_window(tmp_path: Path) -> None:
    """A fresh machine (an empty numba cache): the planner answers every window, no fallback, no traceback.

    Before: the kernels compiled inside the planner's first requests (15-60 s), the windows that came
    meanwhile found it busy and the fallback decided them (10 of 18 in the shipped demo). Now the planner
    warms the kernels up at start-up, before the player starts. 13 frames at 10 Hz played at rate 0.2, a
    window of 4: a planner request every 2 s, a tenth of a second of work on this map once compiled.
    """
    bag = _bag(tmp_path, 13, 64, 48, seed=4)
    run = tmp_path / "run"
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba_cache"), PYTHONUNBUFFERED="1")
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [env.get("PYTHONPATH")])])
    assert env.get("ROS_DOMAIN_ID") and env.get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "LOCALHOST"
    cmd = [sys.executable, "-m", "roigsf_ros.cli", "demo", "--bag", str(bag), "--out", str(run)]
    cmd += ["--rate", "0.2", "--gt-mesh", "", "--no-progress", "--final-iters", "5"]
    cmd += ["--set", "keyframe_selector.window=4", "--set", "mapper.iters_per_keyframe=3"]
    proc = subprocess.run(cmd, env=env, cwd=REPO, capture_output=True, text=True, timeout=280)
    output = proc.stdout + proc.stderr
    assert proc.returncode == 0, output
    assert not TRACEBACK.search(output), output
    assert any((tmp_path / "numba_cache").rglob("*.nbi")), "the demo did not compile into the empty cache"
    metrics: dict[str, Any] = json.loads((run / "metrics.json").read_text())
    assert metrics["planner_calls"] == 3 and metrics["planner_answers"] == 3 and metrics["fallbacks"] == 0, output
    assert metrics["warm_up_s"] > 0
    assert metrics["window_period_s"] == pytest.approx(2.0)  # a window of 4 frames at 10 Hz, played at rate 0.2
    assert 0 < metrics["planner_max_scoring_s"] < 2.0 and "fisher" in metrics["planner_slowest_phases_s"]
    for row in ("planner answers/calls", "fallbacks", "kernel warm-up (s)"):
        assert re.search(rf"^  {re.escape(row)} +\S", proc.stdout, re.MULTILINE), proc.stdout


def test_demo_at_rate_0_keeps_pace_with_its_nodes_and_loses_nothing(tmp_path: Path) -> None:
    """``--rate 0``: every frame reaches the nodes, every window is answered by the planner, every keyframe mapped.

    Before: the player published the whole bag at once; the nodes' queues overflowed (47 of the shipped bag's 150
    frames received) and the windows that came while the planner was busy went to the fallback policy.
    """
    from roigsf_ros.cli import main

    bag = _bag(tmp_path, 25, 64, 48, seed=8)
    run = tmp_path / "run"
    args = ["demo", "--bag", str(bag), "--out", str(run), "--rate", "0", "--gt-mesh", "", "--no-progress",
            "--final-iters", "0", "--set", "keyframe_selector.window=4",
            "--set", "mapper.iters_per_keyframe=3"]  # fmt: skip
    assert main(args) == 0
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["frames_received"] == 25 and metrics["dropped_frames"] == 0
    assert metrics["planner_answers"] == 6 and metrics["fallbacks"] == 0
    assert metrics["planner_calls"] == 6 + metrics["planner_not_ready"]  # a window asked before the first map: again
    assert metrics["keyframes_not_mapped"] == 0 and metrics["n_keyframes"] == 7
    assert metrics["lockstep_stalls"] == 0


def test_lockstep_waits_for_delivery_and_room_and_gives_up_on_a_stall() -> None:
    """The pace of ``--rate 0``: a frame's colour message waits until both camera nodes received everything
    published before it and no window waits behind a planner request; other topics never wait; when nothing
    moves for ``stall_s`` the frame goes anyway, counted.
    """
    from types import SimpleNamespace

    from roigsf_ros.nodes.lockstep import Lockstep

    sel = {"planner_window_waiting": False, "frames_held_for_map": 0, "frames": 0, "keyframes_published": 0}
    sel |= {"planner_answers": 0, "planner_failures": 0, "planner_timeouts": 0, "fallbacks": 0}
    sel |= {"planner_waits_for_map": False, "planner_not_ready": 0, "planner_pending": False}
    mp = {"pending_keyframes": 0, "waiting_keyframes": 0, "keyframe_msgs": 0, "keyframes": 0}
    received = {"/c": 1, "/d": 0}
    cam = SimpleNamespace(stats=lambda: {"in_callback": 0, "received": dict(received)})
    system = SimpleNamespace(
        mapper=SimpleNamespace(camera=cam, status=lambda: mp), selector=SimpleNamespace(camera=cam, status=lambda: sel)
    )
    pace = Lockstep(system, "/c", stall_s=0.3, poll_s=0.01)  # type: ignore[arg-type]
    t0 = time.monotonic()
    pace("/d", {"/c": 1, "/d": 5})  # not a frame's first message: no wait
    pace("/c", {"/c": 1, "/d": 0})  # everything delivered, room: no wait
    assert time.monotonic() - t0 < 0.1 and pace.stalls == 0
    threading.Timer(0.1, lambda: received.update({"/d": 1})).start()
    pace("/c", {"/c": 1, "/d": 1})  # waits for /d's message, then goes
    assert 0.05 < time.monotonic() - t0 < 0.3 and pace.stalls == 0
    sel["planner_window_waiting"] = True  # a window behind a request that never ends: a stall, counted
    t1 = time.monotonic()
    pace("/c", {"/c": 1, "/d": 1})
    assert time.monotonic() - t1 >= 0.3 and pace.stalls == 1
    sel["planner_window_waiting"] = False
    # The window asked waits for the planner's first map, or was asked while the map has no keyframe (its answer may
    # be "not ready"): the next window would send it to the fallback, so the next frame waits.
    for hold in ("planner_waits_for_map", "planner_pending"):
        sel[hold] = True
        threading.Timer(0.1, lambda key=hold: sel.update({key: False})).start()
        t2 = time.monotonic()
        pace("/c", {"/c": 1, "/d": 1})
        assert 0.05 < time.monotonic() - t2 < 0.3 and pace.stalls == 1
    mp["keyframes"], sel["planner_pending"] = 1, True  # a request on a map with a keyframe: frames go on meanwhile
    t3 = time.monotonic()
    pace("/c", {"/c": 1, "/d": 1})
    assert time.monotonic() - t3 < 0.1


def test_demo_counts_the_frames_the_nodes_refuse_and_maps_the_rest(tmp_path: Path) -> None:
    """A frame whose depth image the nodes refuse (an unknown encoding) is counted, not fatal: the nodes map the
    others, and "dropped frames" stays 0 (the frame never was one the nodes could take).

    Before: the demo read the bag for its report, stopped on that frame with an InputError and mapped nothing.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from roigsf_ros.cli import main

    src, bag = _bag(tmp_path, 6, 32, 24, seed=9), tmp_path / "one_bad"
    store = get_typestore(Stores.ROS2_JAZZY)
    with bags.opened_bag(src) as reader, Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns: dict[str, Any] = {}
        seen = 0
        for conn, stamp, raw in reader.messages():
            if conn.topic == bags.DEPTH_TOPIC:
                seen += 1
                if seen == 3:
                    msg = reader.deserialize(raw, conn.msgtype)
                    msg.encoding = "mono8"
                    raw = store.serialize_cdr(msg, conn.msgtype)
            if conn.topic not in conns:
                conns[conn.topic] = writer.add_connection(conn.topic, conn.msgtype, typestore=store)
            writer.write(conns[conn.topic], stamp, bytes(raw))
    run = tmp_path / "run"
    args = ["demo", "--bag", str(bag), "--out", str(run), "--rate", "0", "--gt-mesh", "", "--no-progress",
            "--policy", "every-n", "--final-iters", "0", "--set", "mapper.iters_per_keyframe=2"]  # fmt: skip
    assert main(args) == 0
    metrics = json.loads((run / "metrics.json").read_text())
    assert (metrics["n_frames"], metrics["frames_received"], metrics["dropped_frames"]) == (5, 5, 0), metrics
    assert metrics["bag_frames_refused"] == 1 and "mono8" in metrics["bag_frames_refused_reason"]


def test_demo_decides_the_frames_the_selector_holds_when_the_bag_ends(tmp_path: Path) -> None:
    """With ``lookahead`` the selector holds the last window when the stream ends: the demo calls its ``finish``."""
    from roigsf_ros.cli import main

    bag = _bag(tmp_path, 7, 32, 24, seed=4)
    run = tmp_path / "run"
    args = ["demo", "--bag", str(bag), "--out", str(run), "--rate", "0", "--gt-mesh", "", "--no-progress",
            "--policy", "novelty", "--final-iters", "0", "--set", "keyframe_selector.window=2",
            "--set", "keyframe_selector.lookahead=2", "--set", "mapper.iters_per_keyframe=2"]  # fmt: skip
    assert main(args) == 0
    metrics = json.loads((run / "metrics.json").read_text())
    # frame 0, then windows of 2 decided one trigger late (triggers at frames 2, 4, 6: the first decides nothing),
    # and the frames still held at the end: 1 + 2 + 1
    assert metrics["n_keyframes"] == 4


def test_demo_takes_params_files_in_order_and_policy_over_them(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--params-file`` is repeatable, later files winning; a file's selector policy holds unless ``--policy`` is
    given, and the report names the policy that ran. A file that is no params file is refused before the replay.

    Before: one file only, and the demo passed its ``--policy`` default to the selector as a parameter override,
    which beats a params file: a file's ``keyframe_selector.policy`` was silently ignored.
    """
    from roigsf_ros.cli import main

    bag = _bag(tmp_path, 6, 32, 24, seed=5)
    first, second = tmp_path / "first.yaml", tmp_path / "second.yaml"
    first.write_text("keyframe_selector:\n  ros__parameters:\n    policy: every-n\n    every_n: 2\n")
    second.write_text("keyframe_selector:\n  ros__parameters:\n    every_n: 3\n")
    run = tmp_path / "run"
    args = ["demo", "--bag", str(bag), "--out", str(run), "--rate", "0", "--gt-mesh", "", "--no-progress",
            "--final-iters", "0", "--set", "mapper.iters_per_keyframe=2",
            "--params-file", str(first), "--params-file", str(second)]  # fmt: skip
    assert main(args) == 0
    metrics = json.loads((run / "metrics.json").read_text())
    assert (metrics["policy"], metrics["n_keyframes"]) == ("every-n", 2)  # frames 0 and 3 of 6: every_n 3 won
    assert "(policy every-n)" in capsys.readouterr().out
    assert main([*args, "--policy", "all"]) == 0
    metrics = json.loads((run / "metrics.json").read_text())
    assert (metrics["policy"], metrics["n_keyframes"]) == ("all", 6)
    bad = tmp_path / "bad.yaml"
    bad.write_text("keyframe_selector:\n  policy: every-n\n")  # no ros__parameters level
    capsys.readouterr()
    assert main([*args, "--params-file", str(bad)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "'keyframe_selector/policy': needs a 'ros__parameters' mapping" in err, err
    from roigsf_ros.nodes.node_params import params_file_sections

    namespaced = tmp_path / "namespaced.yaml"  # ROS's other layouts: a wildcard and a namespace level
    namespaced.write_text("/**:\n  ros__parameters:\n    seed: 1\n/ns:\n  mapper:\n    ros__parameters: {}\n")
    assert params_file_sections(namespaced, strict=True) == [
        ("/**", "/**", {"seed": 1}),
        ("/ns/mapper", "/ns/mapper", {}),
    ]
    namespaced.write_text("/ns:\n  mapper:\n    policy: every-n\n")
    with pytest.raises(InputError, match=r"'/ns/mapper/policy': needs a 'ros__parameters' mapping"):
        params_file_sections(namespaced, strict=True)
    assert params_file_sections(namespaced) == []  # not strict (the nodes' own reading): what could be read
    for text, why in (
        ("[1, 2]\n", "a params file maps node names"),
        ("mapper: {ros__parameters: 3}\n", "'mapper': 'ros__parameters' is not a mapping"),
        ("a: [\n", "not a readable YAML params file"),
    ):
        namespaced.write_text(text)
        with pytest.raises(InputError, match=re.escape(why)):
            params_file_sections(namespaced, strict=True)


def test_fallback_hint_says_why_windows_went_to_the_fallback() -> None:
    """When windows went to the fallback the demo says which measured sign explains it: the longest wait for the
    planner's answer outlasting the time between windows (with the slowest request's two largest parts), or frames
    held up before the selector (then a burst of windows); otherwise it says nothing."""
    from roigsf_ros.cli.demo import fallback_hint

    phases = {"map_update": 0.0, "scoring": 1.58, "fisher": 0.8, "unseen": 0.62}
    metrics = {"fallbacks": 2, "selector_max_answer_s": 1.63, "window_period_s": 1.3, "rate": 1.0,
               "planner_slowest_phases_s": phases, "selector_max_frame_gap_s": 0.12,
               "selector_max_novelty_s": 0.3}  # fmt: skip
    hint = fallback_hint(metrics)
    assert hint is not None and "2 window(s)" in hint, hint
    assert "answer took 1.63 s (its slowest request: fisher 0.80 s, unseen 0.62 s)" in hint, hint
    assert "every 1.30 s at rate x1" in hint and "burst" not in hint
    held = {**metrics, "selector_max_answer_s": 0.9, "selector_max_frame_gap_s": 1.35, "selector_max_novelty_s": 1.1}
    hint = fallback_hint(held)  # the planner in time, the frames held up before the selector
    assert hint is not None and "up to 1.35 s apart, then in a burst; its novelty took up to 1.10 s" in hint, hint
    assert "planner's longest" not in hint
    assert fallback_hint({**metrics, "fallbacks": 0}) is None
    assert fallback_hint({**metrics, "selector_max_answer_s": 1.0}) is None  # in time: the fallback had other reasons
    assert fallback_hint({**metrics, "window_period_s": None}) is None  # as fast as possible: no period


def test_mapping_hint_says_how_many_named_keyframes_were_not_mapped_and_why() -> None:
    """The demo's table and a note say when keyframes the selector named never reached the map, by reason; gaus-slam
    live gets the reason its rule names nearly every frame. Before, the table showed the mapped keyframes only."""
    from roigsf_ros.cli.demo import format_table, mapping_hint

    losses = {"keyframes_dropped_overflow": 115, "keyframes_missing": 2, "keyframes_failed": 0}
    metrics = {"keyframes_not_mapped": 117, "keyframe_losses": losses, "keyframes_published": 150,
               "policy": "gaus-slam", "rate": 1.0}  # fmt: skip
    hint = mapping_hint(metrics)
    assert hint is not None and "did not map 117 of the 150 keyframes named" in hint, hint
    assert "115 its keyframe queue was full, 2 their frame was gone" in hint and "failed" not in hint, hint
    assert "map_wait_s 0" in hint
    other = mapping_hint({**metrics, "policy": "roi-gsurfisher"})
    assert other is not None and "more slowly than they came at rate x1" in other and "gaus-slam" not in other
    assert mapping_hint({**metrics, "keyframes_not_mapped": 0}) is None
    assert re.search(r"^  keyframes not mapped +117$", format_table(metrics), re.MULTILINE)


def test_demo_stops_cleanly_on_sigterm(tmp_path: Path) -> None:
    """SIGTERM stops the demo as Ctrl-C does: its nodes stopped, exit 143, "interrupted", no run folder.

    Before: SIGTERM killed the process at once (no clean-up: Fast DDS's shared-memory files were left in /dev/shm).
    """
    bag = _bag(tmp_path, 13, 32, 24, seed=6)
    run = tmp_path / "run"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [env.get("PYTHONPATH")])])
    assert env.get("ROS_DOMAIN_ID") and env.get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "LOCALHOST"
    cmd = [sys.executable, "-m", "roigsf_ros.cli", "demo", "--bag", str(bag), "--out", str(run), "--rate", "0.1",
           "--gt-mesh", "", "--no-progress", "--policy", "every-n", "--final-iters", "0"]  # fmt: skip
    proc = subprocess.Popen(cmd, env=env, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        first = proc.stdout.readline()  # printed once the bag is read, before the nodes start
        assert first.startswith(f"bag {bag}"), first
        time.sleep(4.0)  # the nodes up and the replay under way (13 frames at rate 0.1: 13 s)
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 143, (proc.returncode, out, err)
    assert "roigsf demo: interrupted" in err and not TRACEBACK.search(out + err), err
    assert not run.exists()


def test_demo_says_why_it_fails_when_frames_did_not_reach_the_nodes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Exit 1 with a line naming how many of the bag's frames the nodes did not get (before: exit 1 and the normal
    report, nothing saying why)."""
    from roigsf_ros.cli import demo, main

    bag = _bag(tmp_path, 4, 32, 24, seed=7)
    metrics = {"policy": "every-n", "frames_received": 3, "fallbacks": 0, "keyframes_not_mapped": 0}
    monkeypatch.setattr(demo, "run_demo", lambda *args, **kwargs: metrics)
    assert main(["demo", "--bag", str(bag), "--out", str(tmp_path / "run"), "--rate", "0", "--no-progress"]) == 1
    out, err = capsys.readouterr()
    assert "1 of the bag's 4 frames did not reach the nodes complete and valid (in lockstep (each frame" in err, err
    assert "s; playing in lockstep (each frame once the nodes took the one before) into active_mapping" in out, out
    real_info = demo.bag_info  # the same bag, read as if its stamps went back once: said as the likely cause

    def stamps_back(*args: Any, **kwargs: Any) -> dict[str, Any]:
        return {**real_info(*args, **kwargs), "frames_stamped_back": 1, "first_stamped_back": "frame 3 (...)"}

    monkeypatch.setattr(demo, "bag_info", stamps_back)
    assert main(["demo", "--bag", str(bag), "--out", str(tmp_path / "run"), "--rate", "0", "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert "stamps go back at 1 frame(s), first at frame 3 (...), and the nodes drop a frame stamped before" in err
    metrics["frames_received"] = 4
    assert main(["demo", "--bag", str(bag), "--out", str(tmp_path / "run"), "--rate", "0", "--no-progress"]) == 0


def _robot_bag(root: Path, frames: int, seed: int) -> Path:
    """A small bag as a robot records it (RealSense names, pose only on TF, compressed images)."""
    from roigsf_ros.data.robot_bag import write_robot_bag

    assert write_robot_bag(_bag(root, frames, 32, 24, seed=seed), root / "robot") == frames
    return root / "robot"


def test_demo_maps_a_robot_bag_with_realsense(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--realsense`` reads a robot's bag as the nodes do: every frame received, every keyframe named mapped.

    Before: the demo read the bag with the default topics whatever the nodes were set to, printed "0 frames of
    NonexNone" and failed on the missing /camera/color/image_raw; it had no ``--realsense``.
    """
    from roigsf_ros.cli import main

    bag = _robot_bag(tmp_path, 6, seed=8)
    run = tmp_path / "run"
    args = ["demo", "--bag", str(bag), "--out", str(run), "--rate", "1", "--gt-mesh", "", "--no-progress",
            "--policy", "all", "--final-iters", "0", "--set", "mapper.iters_per_keyframe=2"]  # fmt: skip
    assert main(args) == 2  # the default names: the reader's error, and a hint, before anything starts
    out = capsys.readouterr()
    assert "topic /camera/color/image_raw (sensor_msgs/msg/Image) is missing" in out.err, out.err
    assert "try --realsense" in out.err and "None" not in out.out + out.err and not run.exists(), out
    assert main([*args, "--realsense"]) == 0
    out = capsys.readouterr()
    assert out.out.startswith(f"bag {bag}: 6 frames of 32x24, depth 16UC1; compressedDepth png, pose from tf"), out
    metrics = json.loads((run / "metrics.json").read_text())
    assert (metrics["n_frames"], metrics["frames_received"], metrics["dropped_frames"]) == (6, 6, 0), metrics
    assert (metrics["keyframes_published"], metrics["n_keyframes"], metrics["keyframes_in_bag"]) == (6, 6, 6)
    assert metrics["keyframes_not_mapped"] == 0
    assert metrics["tf_child_frame_note"] is None and metrics["camera_topics"]["pose_source"] == "tf", metrics


def test_demo_names_the_bag_frames_tf_does_not_pose(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A robot's bag with a gap in its TF: the demo said "5 frames" and "dropped frames 0" as if the bag held no
    more; now its first line, its table and metrics.json name the frame TF does not pose, with the reason."""
    from roigsf_ros.cli import main
    from roigsf_ros.data.robot_bag import write_robot_bag

    write_robot_bag(_bag(tmp_path, 6, 32, 24, seed=8), tmp_path / "gap", keep_tf=lambda k: k != 5)
    run = tmp_path / "run"
    args = ["demo", "--bag", str(tmp_path / "gap"), "--out", str(run), "--gt-mesh", "", "--realsense",
            "--no-progress", "--policy", "all", "--final-iters", "0",
            "--set", "mapper.iters_per_keyframe=1"]  # fmt: skip
    assert main(args) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"bag {tmp_path / 'gap'}: 5 frames (and 1 more that TF does not pose: "), out
    assert "frames TF never posed      1" in out
    metrics = json.loads((run / "metrics.json").read_text())
    assert (metrics["n_frames"], metrics["bag_frames_without_tf"], metrics["dropped_frames"]) == (5, 1, 0), metrics
    assert "'odom' -> 'base_link'" in metrics["bag_frames_without_tf_reason"]


def test_demo_refuses_camera_settings_with_which_a_node_reads_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The mapper's and the selector's camera settings (params files, ``--realsense``, ``--set``) are checked against
    the bag before anything starts: one that reads no frame of it is named. ``--set`` wins over ``--realsense``."""
    from roigsf_ros.cli import main

    bag = _robot_bag(tmp_path, 3, seed=9)
    run = tmp_path / "run"
    args = ["demo", "--bag", str(bag), "--out", str(run), "--gt-mesh", "", "--no-progress"]
    robot = {"color_topic": "/camera/color/image_raw", "depth_topic": "/camera/aligned_depth_to_color/image_raw",
             "camera_info_topic": "/camera/color/camera_info", "pose_source": "tf", "color_transport": "compressed",
             "depth_transport": "compressedDepth"}  # fmt: skip
    assert main([*args, *(a for k, v in robot.items() for a in ("--set", f"mapper.{k}={v}"))]) == 2  # mapper only
    err = capsys.readouterr().err
    assert "parameters 'keyframe_selector.depth_topic', 'keyframe_selector.camera_info_topic'" in err, err
    assert "the keyframe_selector would read no frame of the bag" in err, err
    assert main([*args, "--realsense", "--set", "keyframe_selector.depth_transport=raw"]) == 2
    err = capsys.readouterr().err
    assert "parameter 'keyframe_selector.depth_transport': depth_transport=raw (the mapper's: auto, here " \
        "compressedDepth)" in err, err  # fmt: skip
    params = tmp_path / "world.yaml"
    params.write_text("keyframe_selector:\n  ros__parameters:\n    tf_parent_frame: world\n")
    assert main([*args, "--realsense", "--params-file", str(params)]) == 2
    err = capsys.readouterr().err
    assert "parameter 'keyframe_selector.tf_parent_frame': tf_parent_frame=world (the mapper's: map)" in err, err
    assert "without a pose on TF" in err and not run.exists(), err


def test_demo_takes_roigsf_maps_camera_options_on_both_camera_nodes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The demo had ``--realsense`` alone: a robot whose camera frame is not RealSense's needed two ``--set`` (one per
    camera node). Now it takes ``roigsf map``'s camera options, each set on the mapper and the selector (the camera
    info topic on the planner too), over ``--realsense``'s names and under a ``--set``; a bad value names its option.
    """
    from roigsf_ros.cli import main
    from roigsf_ros.cli.demo import with_camera_options
    from roigsf_ros.data.bags import CAMERA_FRAME_ID

    bag = _robot_bag(tmp_path, 3, seed=10)
    run = tmp_path / "run"
    args = ["demo", "--bag", str(bag), "--out", str(run), "--gt-mesh", "", "--no-progress", "--policy", "all",
            "--final-iters", "0", "--rate", "1", "--set", "mapper.iters_per_keyframe=1"]  # fmt: skip
    assert main([*args, "--realsense", "--tf-child-frame", "camera_link_optical"]) == 2  # refused before the start
    err = capsys.readouterr().err
    assert "'camera_link_optical'" in err and CAMERA_FRAME_ID in err and not run.exists(), err
    assert main([*args, "--realsense", "--tf-tolerance", "-1"]) == 2
    assert "roigsf demo: error: --tf-tolerance: " in capsys.readouterr().err
    names = ["--color-topic", "/camera/color/image_raw", "--depth-topic", "/camera/aligned_depth_to_color/image_raw",
             "--camera-info-topic", "/camera/color/camera_info", "--pose-source", "tf",
             "--tf-child-frame", CAMERA_FRAME_ID, "--color-transport", "compressed",
             "--depth-transport", "auto"]  # fmt: skip
    assert main([*args, *names]) == 0, capsys.readouterr().err  # what --realsense sets, one option at a time
    metrics = json.loads((run / "metrics.json").read_text())
    assert (metrics["n_frames"], metrics["frames_received"], metrics["keyframes_not_mapped"]) == (3, 3, 0), metrics
    from roigsf_ros.cli import build_parser

    parsed = build_parser().parse_args(["demo", "--tf-child-frame", "cam", "--camera-info-topic", "/ci",
                                        "--set", "keyframe_selector.tf_child_frame=other"])  # fmt: skip
    assert with_camera_options({"mapper": {"iters_per_keyframe": 2}}, parsed) == {
        "mapper": {"tf_child_frame": "cam", "camera_info_topic": "/ci", "iters_per_keyframe": 2},
        "keyframe_selector": {"tf_child_frame": "cam", "camera_info_topic": "/ci"},
        "nbv_planner": {"camera_info_topic": "/ci"},
    }
    over = with_camera_options({"keyframe_selector": {"tf_child_frame": "other"}}, parsed)
    assert over["keyframe_selector"]["tf_child_frame"] == "other"  # a --set wins


def test_demo_refuses_a_set_value_of_the_wrong_type_before_anything_starts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """``--set mapper.iters_per_keyframe=abc`` was refused by the mapper node once the nodes had started and warmed
    their kernels up: a method setting (MapperConfig's, NBVConfig's: the node parameters of the same names) of the
    wrong type is refused with the bag unread; names the nodes alone declare are still theirs to check."""
    from roigsf_ros.cli import main
    from roigsf_ros.cli.demo import parse_sets

    started: list[str] = []
    monkeypatch.setattr("roigsf_ros.cli.demo.demo_camera", lambda *a, **k: started.append("bag read") or 1 / 0)
    for item, words in (("mapper.iters_per_keyframe=abc", "must be a whole number, got 'abc'"),
                        ("nbv_planner.unseen_weight=high", "must be a number, got 'high'")):  # fmt: skip
        assert main(["demo", "--out", str(tmp_path / "run"), "--no-progress", "--set", item]) == 2
        err = capsys.readouterr().err
        assert f"roigsf demo: error: --set {item}: {words}" in err, err
    assert started == [] and not (tmp_path / "run").exists()
    assert parse_sets(["keyframe_selector.window=abc", "mapper.iters_per_keyframe=12"]) == {
        "keyframe_selector": {"window": "abc"},
        "mapper": {"iters_per_keyframe": 12},
    }


def test_demo_defaults_to_the_sample_bag_and_mesh_from_any_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """``roigsf demo`` run outside the repository root failed with ``bags/synth_room: bag not found``: the default
    bag and mesh were relative to the working folder. They are now the checkout's sample, else the installed one
    (setup.py puts bags/ into share/roigsf_ros/)."""
    from roigsf_ros.cli import demo, main
    from roigsf_ros.core import package_files

    used: dict[str, Any] = {}

    def fake_run_demo(bag: Path, out: Path, **kwargs: Any) -> dict[str, Any]:
        used.update(bag=bag, gt_mesh=kwargs["gt_mesh"])
        return {"policy": "every-n", "frames_received": 150, "fallbacks": 0, "keyframes_not_mapped": 0}

    monkeypatch.setattr(demo, "run_demo", fake_run_demo)
    monkeypatch.chdir(tmp_path)
    assert main(["demo", "--out", str(tmp_path / "run"), "--no-progress"]) == 0
    assert used == {"bag": REPO / "bags" / "synth_room", "gt_mesh": REPO / "bags" / "synth_room_mesh.ply"}
    # installed (no checkout beside the modules): the share folder's copy
    share = tmp_path / "share" / "roigsf_ros"
    (share / "bags").mkdir(parents=True)
    (share / "bags" / "synth_room").symlink_to(REPO / "bags" / "synth_room")
    (share / "bags" / "synth_room_mesh.ply").symlink_to(REPO / "bags" / "synth_room_mesh.ply")
    monkeypatch.setattr(package_files, "CHECKOUT_ROOT", tmp_path / "site-packages")
    monkeypatch.setattr(package_files, "share_folders", lambda: [share])
    assert main(["demo", "--out", str(tmp_path / "run"), "--no-progress", "--gt-mesh", ""]) == 0
    assert used == {"bag": share / "bags" / "synth_room", "gt_mesh": None}
    assert "bag " + str(share / "bags" / "synth_room") + ": 150 frames" in capsys.readouterr().out
    # scripts/demo.sh: the installed roigsf given the checkout's bag takes the mesh beside it (the share folder's
    # before: the same bytes, but the start line named two places)
    out = ["--out", str(tmp_path / "run"), "--no-progress"]
    assert main(["demo", "--bag", str(REPO / "bags" / "synth_room"), *out]) == 0
    assert used == {"bag": REPO / "bags" / "synth_room", "gt_mesh": REPO / "bags" / "synth_room_mesh.ply"}
    mcap = next((REPO / "bags" / "synth_room").glob("*.mcap"))
    assert main(["demo", "--bag", str(mcap), *out]) == 0
    assert used["gt_mesh"] == REPO / "bags" / "synth_room_mesh.ply"


def test_the_installed_package_carries_the_sample_bag_and_mesh() -> None:
    """setup.py's data files put the sample into the interpreter's share folder (where ``sample_path`` looks when no
    checkout is beside the modules): the same files as the checkout's."""
    share = Path(sys.prefix) / "share" / "roigsf_ros"
    if not (share / "package.xml").is_file():
        pytest.skip(
            f"roigsf_ros is not pip-installed into this interpreter ({share} is missing; scripts/setup.sh does it)"
        )
    for name in ("synth_room/metadata.yaml", "synth_room/synth_room.mcap", "synth_room_mesh.ply"):
        installed, checkout = share / "bags" / name, REPO / "bags" / name
        assert installed.is_file(), f"{installed} missing: setup.py's data_files do not install the sample"
        assert installed.read_bytes() == checkout.read_bytes(), f"{installed} differs from {checkout}: reinstall"
