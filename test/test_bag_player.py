"""bag_player: every message arrives byte-identical and in order, timing follows the rate factor, main() exits."""

from __future__ import annotations

import os
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("rclpy")

from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from roigsf_ros.core.errors import InputError
from roigsf_ros.data import bags
from roigsf_ros.data.replica import ReplicaSequence
from roigsf_ros.nodes.bag_player import BagPlayer, message_class, progress_line, reliable_qos
from roigsf_ros.perf.io import make_synthetic_replica

pytestmark = pytest.mark.ros
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """5 frames of 32x24 (20 messages on 4 topics) recorded at 10 Hz."""
    root = tmp_path_factory.mktemp("player")
    make_synthetic_replica(root / "scene", 32, 24, 5, seed=5)
    out = root / "bag"
    bags.write_bag(ReplicaSequence(root / "scene"), out, rate_hz=10.0, progress=False)
    return out


@pytest.fixture(scope="module")
def bag20hz(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """10 frames of 16x12 recorded at 20 Hz: 0.45 s from the first stamp to the last."""
    root = tmp_path_factory.mktemp("player20")
    make_synthetic_replica(root / "scene", 16, 12, 10, seed=6)
    out = root / "bag"
    bags.write_bag(ReplicaSequence(root / "scene"), out, rate_hz=20.0, progress=False)
    return out


def _bag_messages(path: Path) -> tuple[dict[str, str], dict[str, list[bytes]]]:
    with bags.open_any_reader(path) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        raws: dict[str, list[bytes]] = {t: [] for t in types}
        for conn, _, raw in reader.messages():
            raws[conn.topic].append(bytes(raw))
    return types, raws


def _player(ctx: Any, bag: Path, **params: Any) -> BagPlayer:
    """A player of ``bag``; no wait for subscribers unless ``wait_for_subscribers`` is given (most tests have none)."""
    params = {"progress_period_s": 0.2, "wait_for_subscribers": 0, **params}
    overrides = [Parameter("bag", value=str(bag))]
    overrides += [Parameter(name, value=value) for name, value in params.items()]
    return BagPlayer(context=ctx, parameter_overrides=overrides)


@contextmanager
def _spinning(ctx: Any, *nodes: Any) -> Iterator[None]:
    """Spin ``nodes`` on one executor in a thread; shut it down, join it and destroy the nodes on exit."""
    executor = SingleThreadedExecutor(context=ctx)
    for node in nodes:
        executor.add_node(node)
    thread = threading.Thread(target=executor.spin, name="test_executor")
    thread.start()
    try:
        yield
    finally:
        executor.shutdown()
        thread.join(timeout=10)
        assert not thread.is_alive()
        for node in nodes:
            node.destroy_node()


def test_every_message_arrives_in_order_with_identical_payload(ros_context: Any, bag: Path) -> None:
    import rclpy

    types, expected = _bag_messages(bag)
    received: dict[str, list[bytes]] = {t: [] for t in types}
    sink = rclpy.create_node("test_sink", context=ros_context)
    for topic, typ in types.items():
        sink.create_subscription(
            message_class(typ), topic, lambda msg, out=received[topic]: out.append(msg), reliable_qos(100), raw=True
        )
    player = _player(ros_context, bag, rate=0.0, start_delay_s=0.5, wait_for_subscribers=1)
    with _spinning(ros_context, sink, player):
        assert player.wait(30.0), "playback did not finish"
        deadline = time.monotonic() + 10.0
        while sum(map(len, received.values())) < 20 and time.monotonic() < deadline:
            time.sleep(0.02)
        summary = player.summary()
    assert summary["published"] == 20 and summary["loops_completed"] == 1 and summary["error"] is None
    for topic in types:
        assert received[topic] == expected[topic], f"{topic}: payloads differ or arrived out of order"
        stamps = [struct.unpack_from("<iI", raw, 4) for raw in received[topic]]
        assert stamps == sorted(stamps) and len(set(stamps)) == 5


def _sink(ctx: Any, name: str, types: dict[str, str], received: dict[str, list[bytes]]) -> Any:
    """A node subscribed (reliable, raw) to every topic of ``types``, appending to ``received``."""
    import rclpy

    sink = rclpy.create_node(name, context=ctx)
    for topic, typ in types.items():
        sink.create_subscription(
            message_class(typ), topic, lambda msg, out=received[topic]: out.append(msg), reliable_qos(100), raw=True
        )
    return sink


def test_pace_runs_before_each_message_at_rate_0_with_the_counts_so_far(ros_context: Any, bag: Path) -> None:
    """At rate 0 a ``pace`` callable is called before every message with its topic and what was published before
    it, in the playback thread, and each message waits for it to return (how ``roigsf demo --rate 0`` keeps its
    nodes' queues from overflowing).
    """
    calls: list[tuple[str, dict[str, int]]] = []
    player: BagPlayer | None = None
    built = threading.Event()  # the playback thread starts in the constructor: it may pace before ``player`` is set

    def pace(topic: str, published: Any) -> None:
        assert built.wait(10.0), "the player's constructor did not return"
        assert player is not None and player.published == sum(published.values())  # nothing goes before we return
        calls.append((topic, dict(published)))
        time.sleep(0.002)

    overrides = [Parameter("bag", value=str(bag)), Parameter("rate", value=0.0)]
    overrides += [Parameter("wait_for_subscribers", value=0), Parameter("start_delay_s", value=0.0)]
    player = BagPlayer(context=ros_context, parameter_overrides=overrides, pace=pace)
    built.set()
    with _spinning(ros_context, player):
        assert player.wait(30.0), "playback did not finish"
        summary = player.summary()
    assert summary["published"] == 20 and len(calls) == 20
    types, _ = _bag_messages(bag)
    assert summary["published_by_topic"] == dict.fromkeys(types, 5)
    for n, (topic, before) in enumerate(calls):
        assert sum(before.values()) == n and topic in types


def test_waits_for_subscribers_before_the_first_message(ros_context: Any, bag: Path) -> None:
    """Nothing is published until every topic has a matched subscriber; then all of it arrives, the first included.

    Before: the player published after ``start_delay_s`` whoever listened, and a subscriber in another process
    that DDS had not matched yet lost the first frames (a 20-frame bag into active_mapping: no keyframe).
    """
    types, expected = _bag_messages(bag)
    received: dict[str, list[bytes]] = {t: [] for t in types}
    player = _player(ros_context, bag, rate=0.0, start_delay_s=0.0, wait_for_subscribers=1, wait_timeout_s=60.0)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(player)
    thread = threading.Thread(target=executor.spin, name="test_executor")
    thread.start()
    sink = None
    try:
        time.sleep(1.5)
        assert player.published == 0 and not player.done  # no subscriber yet: waiting
        sink = _sink(ros_context, "test_late_sink", types, received)
        executor.add_node(sink)
        assert player.wait(30.0), "playback did not finish"
        deadline = time.monotonic() + 10.0
        while sum(map(len, received.values())) < 20 and time.monotonic() < deadline:
            time.sleep(0.02)
        summary = player.summary()
    finally:
        executor.shutdown()
        thread.join(timeout=10)
        assert not thread.is_alive()
        player.destroy_node()
        if sink is not None:
            sink.destroy_node()
    assert summary["subscribers_matched"] is True and summary["subscriber_wait_s"] >= 1.5
    assert received == expected  # every message, from the first, in order


def test_rate_factor_sets_the_timing(ros_context: Any, bag20hz: Path) -> None:
    span_s = 0.45  # 10 frames at 20 Hz; every message is due at start + (stamp - first) / rate
    for rate in (1.0, 2.0):
        player = _player(ros_context, bag20hz, rate=rate, start_delay_s=0.0)
        try:
            assert player.wait(30.0)
            assert player.published == 40 and player.error is None
            # Scheduling can only delay a message, never publish it early: a strict lower bound.
            assert span_s / rate - 1e-3 <= player.play_duration_s < span_s / rate + 2.0
        finally:
            player.destroy_node()
    player = _player(ros_context, bag20hz, rate=0.0, start_delay_s=0.0)
    try:
        assert player.wait(30.0) and player.published == 40
    finally:
        player.destroy_node()


def test_topic_filter_and_loop_until_stopped(ros_context: Any, bag: Path) -> None:
    player = _player(ros_context, bag, rate=0.0, start_delay_s=0.0, loop=True, topics=[bags.POSE_TOPIC])
    try:
        deadline = time.monotonic() + 20.0
        while player.loops_completed < 3 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert player.loops_completed >= 3 and not player.done
        assert player.total_per_loop == 5 and player.summary()["topics"] == [bags.POSE_TOPIC]
    finally:
        player.destroy_node()
    assert player.done and player.error is None


def test_bad_parameters_name_the_problem(ros_context: Any, bag: Path, tmp_path: Path) -> None:
    with pytest.raises(InputError, match="bag not found") as exc:
        _player(ros_context, tmp_path / "missing_bag")
    assert "missing_bag" in str(exc.value)
    with pytest.raises(InputError, match=r"/nope.*not in the bag"):
        _player(ros_context, bag, topics=["/nope"])
    with pytest.raises(InputError, match="no bag given"):
        BagPlayer(context=ros_context)
    with pytest.raises(InputError, match=r"wait_for_subscribers.*>= 0"):
        _player(ros_context, bag, wait_for_subscribers=-1)
    with pytest.raises(InputError, match=r"wait_timeout_s.*>= 0"):
        _player(ros_context, bag, wait_timeout_s=float("nan"))


def test_non_finite_rate_and_times_are_refused_naming_the_parameter(ros_context: Any, bag: Path) -> None:
    """``rate:=nan`` played everything at once ("at rate xnan"); nan start/ack delays passed as 0, inf ones hung."""
    for name in ("rate", "start_delay_s", "progress_period_s", "ack_timeout_s"):
        for value in (float("nan"), float("inf"), float("-inf")):
            with pytest.raises(InputError, match=rf"^parameter 'bag_player.{name}': must be a finite number, got"):
                _player(ros_context, bag, **{name: value})


def _run_main(*ros_args: str, plain: tuple[str, ...] = (), module: str = "bag_player") -> subprocess.CompletedProcess:
    env = dict(os.environ)
    assert env.get("ROS_DOMAIN_ID") and env.get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "LOCALHOST"
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [env.get("PYTHONPATH")])])
    cmd = [sys.executable, "-m", f"roigsf_ros.nodes.{module}", *plain, *(("--ros-args", *ros_args) if ros_args else ())]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=60, cwd=REPO)


def test_main_takes_the_bag_as_a_positional_argument(bag: Path) -> None:
    """``bag_player BAG``, as ``ros2 bag play BAG`` (before: "no bag given", exit 2). Its start-up line names the
    topics as published, remapped (a walk: it named none, so a player's remap could not be checked)."""
    proc = _run_main("-p", "rate:=0.0", "-p", "start_delay_s:=0.2", "-p", "wait_for_subscribers:=0",
                     "-r", "/camera/color/image_raw:=/my/rgb", plain=(str(bag),))  # fmt: skip
    output = proc.stdout + proc.stderr
    assert proc.returncode == 0, output
    assert "finished: published 20 messages on 4 topics" in output
    assert "topics as published (remapped): /camera/camera_info, /camera/depth/image_raw, /camera/pose, /my/rgb" \
        in output, output  # fmt: skip


_CONSOLE = (
    "import atexit, sys\n"
    "heavy = ('torch', 'open3d', 'rosbags', 'numba')\n"
    "atexit.register(lambda: print('heavy modules loaded:', [m for m in heavy if m in sys.modules], file=sys.stderr))\n"
    "from roigsf_ros.nodes.console import main\n"
    "sys.exit(main(sys.argv))\n"
)
"""What an installed console script runs (``roigsf_ros.nodes.console``); at exit it says which heavy modules loaded."""


def _run_console(program: str, *args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    assert env.get("ROS_DOMAIN_ID") and env.get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "LOCALHOST"
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [env.get("PYTHONPATH")])])
    cmd = [sys.executable, "-c", _CONSOLE, program, *args]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=60, cwd=REPO)


@pytest.mark.parametrize("program", ["bag_player", "mapper", "nbv_planner", "keyframe_selector", "active_mapping"])
def test_help_prints_help_and_exits_0_without_starting_a_node(program: str, capsys: pytest.CaptureFixture[str]) -> None:
    """``--help`` on every console script (before: the nodes started and ran until killed), answered before the
    node's module loads (before: 4-5 s of importing torch, open3d and rosbags first), as the node's ``main`` answers.
    """
    import importlib

    from roigsf_ros.nodes.console import PROGRAMS

    proc = _run_console(program, "--help")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.startswith(f"usage: {program}") and "-p NAME:=VALUE" in proc.stdout
    assert "[INFO]" not in proc.stdout + proc.stderr  # no node was made
    assert "heavy modules loaded: []" in proc.stderr, proc.stderr
    with pytest.raises(SystemExit) as done:
        importlib.import_module(PROGRAMS[program]).main([program, "--help"])
    assert done.value.code == 0 and capsys.readouterr().out == proc.stdout
    bad = _run_console(program, "--no-such-option")
    assert bad.returncode == 2 and "unrecognized arguments: --no-such-option" in bad.stderr
    assert "heavy modules loaded: []" in bad.stderr, bad.stderr


def test_every_console_script_of_setup_py_is_a_console_entry() -> None:
    """setup.py's node scripts all go through ``roigsf_ros.nodes.console``, one function per program."""
    import re

    from roigsf_ros.nodes import console

    scripts = dict(re.findall(r'"(\w+) = ([\w.:]+)"', (REPO / "setup.py").read_text()))
    nodes = {name: target for name, target in scripts.items() if name != "roigsf"}
    assert nodes == {name: f"roigsf_ros.nodes.console:{name}" for name in console.PROGRAMS}
    assert all(callable(getattr(console, name)) for name in console.PROGRAMS)


def test_main_plays_and_exits_0(bag: Path) -> None:
    no_wait = ("-p", "wait_for_subscribers:=0")
    proc = _run_main("-p", f"bag:={bag}", "-p", "rate:=0.0", "-p", "start_delay_s:=0.2", *no_wait)
    output = proc.stdout + proc.stderr
    assert proc.returncode == 0, output
    assert "finished: published 20 messages on 4 topics" in output


def test_main_without_subscribers_says_so_after_the_timeout_and_plays(bag: Path) -> None:
    """No subscriber within ``wait_timeout_s``: a warning naming every topic short of one, then playback, exit 0."""
    t0 = time.monotonic()
    proc = _run_main("-p", f"bag:={bag}", "-p", "rate:=0.0", "-p", "start_delay_s:=0.0", "-p", "wait_timeout_s:=1.0")
    output = proc.stdout + proc.stderr
    assert proc.returncode == 0, output
    assert "after 1 s (wait_timeout_s), topics still short of the 1 subscriber(s)" in output
    for topic in (bags.CameraTopics().color, bags.CameraTopics().depth, bags.POSE_TOPIC):
        assert f"{topic} (0)" in output
    assert "playing anyway" in output and "finished: published 20 messages on 4 topics" in output
    assert "wait longer with -p wait_timeout_s:=30.0" in output  # the hint for nodes still starting
    assert time.monotonic() - t0 >= 1.0


def test_main_nan_rate_exits_2_naming_the_parameter(bag: Path) -> None:
    """``-p rate:=nan``: a one-line error naming 'rate' and exit 2 before anything is published (it played)."""
    proc = _run_main("-p", f"bag:={bag}", "-p", "rate:=nan", "-p", "wait_for_subscribers:=0")
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert "parameter 'bag_player.rate': must be a finite number, got nan" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert "published" not in proc.stdout + proc.stderr


def test_main_bad_path_exits_nonzero_naming_it(tmp_path: Path) -> None:
    missing = tmp_path / "no_such_bag"
    proc = _run_main("-p", f"bag:={missing}")
    assert proc.returncode != 0
    assert str(missing) in proc.stderr and "bag not found" in proc.stderr


def test_progress_reports_a_finished_loop_as_complete() -> None:
    """After a loop's last message (the closing delay, or before the next loop) the loop reads 100 %, not the next
    loop at 0 % ("0.0% (0/600 messages), 600 published" was logged at the end of every replay)."""
    assert progress_line(300, 0, 600, looping=False) == " 50.0% (300/600 messages), 300 published"
    assert progress_line(600, 1, 600, looping=False) == "100.0% (600/600 messages), 600 published"
    assert progress_line(600, 1, 600, looping=True) == "100.0% (600/600 messages, loop 1), 600 published"
    assert progress_line(750, 1, 600, looping=True) == " 25.0% (150/600 messages, loop 2), 750 published"
    assert progress_line(0, 0, 600, looping=False) == "  0.0% (0/600 messages), 0 published"
