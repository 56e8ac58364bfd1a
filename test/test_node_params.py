"""The nodes' parameter checks (node_params.py): where the package's params files are found, how a bad value's error
reads (its type, its range, the params file that set it), and the warning for a params file's misspelt node section."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("rclpy")

import rclpy
from rcl_interfaces.msg import IntegerRange, ParameterDescriptor
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node
from rclpy.parameter import Parameter

from roigsf_ros.core import package_files
from roigsf_ros.core.errors import InputError
from roigsf_ros.mapping.mapper import MapperConfig
from roigsf_ros.nodes.bag_player import BagPlayer
from roigsf_ros.nodes.keyframe_selector import KeyframeSelectorNode
from roigsf_ros.nodes.mapper import MapperNode
from roigsf_ros.nodes.node_params import (
    PACKAGE_CONFIG_FILES,
    package_parameter_names,
    parameter_error,
    remember_ros_args,
)

pytestmark = pytest.mark.ros
REPO = Path(__file__).resolve().parents[1]


@contextmanager
def _context(*ros_args: str) -> Iterator[Any]:
    """A fresh rclpy Context on this run's domain, started with ``--ros-args ROS_ARGS`` as a console script is (its
    arguments noted, as ``init_ros`` notes them), shut down on exit."""
    args = ["test", "--ros-args", *ros_args]
    ctx = rclpy.Context()
    rclpy.init(args=args, context=ctx, domain_id=int(os.environ["ROS_DOMAIN_ID"]))
    remember_ros_args(ctx, args)
    try:
        yield ctx
    finally:
        ctx.try_shutdown()


def _params(path: Path, node: str, **values: Any) -> str:
    """Write a params file setting ``values`` for ``node``; returns its path as a string."""
    lines = [f"{node}:", "  ros__parameters:", *(f"    {k}: {v}" for k, v in values.items())]
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def _error(build: Any) -> str:
    """The message of the InputError ``build()`` raises."""
    with pytest.raises(InputError) as caught:
        build()
    return str(caught.value)


# ---------------------------------------------------------------------------------------- 1: installed, no ament env
def test_package_parameter_names_are_found_in_the_share_dir_under_the_interpreters_prefix(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``.venv/bin/mapper --ros-args -p unseen_weight:=2.0`` without AMENT_PREFIX_PATH warned that no roigsf node
    declares unseen_weight: installed, the module has no checkout's config/ beside it and the ament index needs the
    variable, so the names came back empty. setup.py installs config/*.yaml to share/roigsf_ros/config under the
    interpreter's prefix (the venv), which is now read as well."""
    monkeypatch.setattr(package_files, "CHECKOUT_ROOT", tmp_path / "no_checkout")
    monkeypatch.delenv("AMENT_PREFIX_PATH", raising=False)
    monkeypatch.setattr(sys, "prefix", str(tmp_path / "prefix"))
    share = tmp_path / "prefix" / "share" / "roigsf_ros" / "config"
    package_parameter_names.cache_clear()
    try:
        assert package_parameter_names() == frozenset()  # nothing anywhere: no names (every override then warns)
        share.mkdir(parents=True)
        for name in PACKAGE_CONFIG_FILES:
            shutil.copy(REPO / "config" / name, share / name)
        package_parameter_names.cache_clear()
        names = package_parameter_names()
        assert {"unseen_weight", "iters_per_keyframe", "window", "rate"} <= names, sorted(names)
    finally:
        package_parameter_names.cache_clear()


# ---------------------------------------------------------------------------------------- 2: the errors' words
def test_a_type_error_hints_at_a_decimal_point_only_for_an_int_and_names_its_params_file(tmp_path: Path) -> None:
    """``lr_means: fast`` was told "(a float parameter needs a decimal point, e.g. 1.0)", twice over; that hint is
    now for an int given to a float parameter only, in ``-p``'s syntax where ``-p`` gave it, and a value from a
    params file names the file."""
    fast = _params(tmp_path / "fast.yaml", "mapper", lr_means="fast")
    with _context("--params-file", fast) as ctx:
        said = _error(lambda: MapperNode(context=ctx))
    assert said == f"parameter 'mapper.lr_means': must be a float like its default 0.0002, got 'fast' (set in {fast})"
    with _context("-p", "lr_means:=1") as ctx:
        said = _error(lambda: MapperNode(context=ctx))
    assert said == (
        "parameter 'mapper.lr_means': must be a float like its default 0.0002, got 1 "
        "(write a float with a point, e.g. -p lr_means:=1.0)"
    )
    one = _params(tmp_path / "one.yaml", "mapper", lr_means=1)
    with _context("--params-file", one, "-p", "lr_means:=2") as ctx:  # the later one sets it: not the file
        said = _error(lambda: MapperNode(context=ctx))
    assert said.endswith("got 2 (write a float with a point, e.g. -p lr_means:=2.0)") and one not in said
    with _context("-p", "lr_means:=2", "--params-file", one) as ctx:
        said = _error(lambda: MapperNode(context=ctx))
    assert said.endswith(f"got 1 (set in {one}; write a float with a point, e.g. 1.0)")


def test_an_out_of_range_value_says_the_allowed_range_and_its_params_file(tmp_path: Path) -> None:
    """ "mapper.iters_per_keyframe: value -5 is out of range" said neither what is allowed nor, from a params file,
    which file set it; the nodes' own checks (check_positive) named no file either."""
    bad = _params(tmp_path / "bad.yaml", "mapper", iters_per_keyframe=-5)
    with _context("--params-file", bad) as ctx:
        said = _error(lambda: MapperNode(context=ctx))
    assert said == f"parameter 'mapper.iters_per_keyframe': must be >= 0, got -5 (set in {bad})"
    with _context("-p", "init_opacity:=1.0") as ctx:
        assert _error(lambda: MapperNode(context=ctx)) == "parameter 'mapper.init_opacity': must be in (0, 1), got 1.0"
    depth = _params(tmp_path / "depth.yaml", "/**", qos_depth=-5)
    with _context("--params-file", depth) as ctx:
        assert (
            _error(lambda: MapperNode(context=ctx))
            == f"parameter 'mapper.qos_depth': must be > 0, got -5 (set in {depth})"
        )
    with pytest.raises(InputError, match=r"^mapper\.prune_opacity: must be in \[0, 1\), got 1\.0$"):
        MapperConfig(prune_opacity=1.0)
    with pytest.raises(InputError, match=r"^mapper\.max_depth_m: must be > min_depth_m and near_m \(0\.5\), got 0\.4$"):
        MapperConfig(near_m=0.5, max_depth_m=0.4)  # a bound set by other fields
    with pytest.raises(InputError, match=r"^mapper\.lr_means: must be a finite number >= 0, got nan$"):
        MapperConfig(lr_means=float("nan"))


def test_rclpy_parameter_errors_read_as_the_nodes_own(ros_context: Any) -> None:
    """rclpy's own errors (a descriptor's range, a type refused outside :func:`declare`) in the nodes' words: the range
    said ("Parameter depth out of range. Min: 1, Max: 10" before), the float hint only for an int."""
    node = Node("ranged", context=ros_context, parameter_overrides=[Parameter("depth", value=-5)])
    one_to_ten = ParameterDescriptor(integer_range=[IntegerRange(from_value=1, to_value=10)])
    try:
        with pytest.raises(InvalidParameterValueException) as caught:
            node.declare_parameter("depth", 5, one_to_ten)
        assert str(parameter_error(node, caught.value)) == "parameter 'ranged.depth': must be in [1, 10], got -5"
    finally:
        node.destroy_node()
    as_int = InvalidParameterTypeException(Parameter("rate", value=1), Parameter.Type.DOUBLE)
    assert str(parameter_error(None, as_int)) == (
        "parameter 'rate': must be a float, got 1 (write a float with a point, e.g. 1.0)"
    )
    word = InvalidParameterTypeException(Parameter("rate", value="fast"), Parameter.Type.DOUBLE)
    assert str(parameter_error(None, word)) == "parameter 'rate': must be a float, got 'fast'"


def test_bag_player_errors_are_worded_as_the_other_nodes(ros_context: Any, tmp_path: Path) -> None:
    """The player's type errors were rclpy's ("Trying to set parameter 'rate' to '1' ...") with "e.g. rate:=1.0"
    even for a value from a YAML file; now as the other nodes' (its console script's too, which notes its
    arguments: the file named)."""
    with pytest.raises(InputError, match=r"^parameter 'bag_player\.rate': must be a float like its default 1\.0, got "
                       r"'fast'$"):  # fmt: skip
        BagPlayer(context=ros_context, parameter_overrides=[Parameter("rate", value="fast")])
    one = _params(tmp_path / "player.yaml", "bag_player", rate=1)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])]))
    cmd = [sys.executable, "-m", "roigsf_ros.nodes.bag_player", "--ros-args", "--params-file", one]
    proc = subprocess.run(cmd, env=env, cwd=REPO, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert proc.stderr.strip() == (
        f"bag_player: error: parameter 'bag_player.rate': must be a float like its default 1.0, got 1 (set in {one}; "
        "write a float with a point, e.g. 1.0)"
    )


# ---------------------------------------------------------------------------------------- 3: a misspelt section
def test_a_params_file_section_close_to_the_nodes_name_is_warned_about(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """``mappr:`` in a params file was ignored without a word (a section applies only to the node it names): the
    node now warns at start-up, once per such section, naming the file; a wildcard, the node's own section and
    another roigsf node's are no misspellings."""
    params = tmp_path / "typo.yaml"
    params.write_text(
        "mappr:\n  ros__parameters:\n    iters_per_keyframe: 5\n"
        "/**:\n  ros__parameters:\n    frame_id: map\n"
        "mapper:\n  ros__parameters:\n    final_iters: 0\n"
        "nbv_planner:\n  ros__parameters:\n    top_k: 3\n"
        "keyframe_selecter:\n  ros__parameters:\n    window: 3\n"
    )
    with _context("--params-file", str(params)) as ctx:
        mapper = MapperNode(context=ctx)
        selector = KeyframeSelectorNode(context=ctx)
        try:
            assert mapper.config.iters_per_keyframe == MapperConfig().iters_per_keyframe  # not applied
            assert selector.window == 8
        finally:
            mapper.destroy_node()
            selector.destroy_node()
    err = capfd.readouterr().err
    warnings = [line.split("]: ", 1)[1] for line in err.splitlines() if "looks like a misspelling" in line]
    assert warnings == [
        f"section 'mappr' in {params} looks like a misspelling of 'mapper': its parameters are not applied",
        f"section 'keyframe_selecter' in {params} looks like a misspelling of 'keyframe_selector': its parameters "
        "are not applied",
    ], err


def test_a_later_params_file_that_changes_a_values_type_is_refused_not_dropped(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """``--params-file config/nbv.yaml --params-file mine.yaml`` with ``unseen_weight: "2.0"`` in mine.yaml ran on
    nbv.yaml's 0.0 without a word: rcl keeps an earlier file's value when a later file gives another type (mine.yaml
    alone was refused). Now refused at start-up, naming both files, before the node's start-up work and log line
    (they ran first: the log said "mapping keyframes named on ..." and then the node refused); a later value of the
    same type still wins."""
    first = _params(tmp_path / "first.yaml", "mapper", iters_per_keyframe=7)
    capfd.readouterr()
    for later, words in (("'ten'", "must be an int, got 'ten'"), ("4.5", "must be an int, got 4.5")):
        second = _params(tmp_path / "second.yaml", "mapper", iters_per_keyframe=later)
        with _context("--params-file", first, "--params-file", second) as ctx, pytest.raises(InputError) as caught:
            MapperNode(context=ctx)
        assert str(caught.value) == (
            f"parameter 'mapper.iters_per_keyframe': {words} (set in {second}; ROS kept 7 from {first} instead, as a "
            "later params file cannot change the type of a value an earlier one set)"
        )
    err = capfd.readouterr().err
    assert "mapping keyframes named" not in err and "mapping kernels ready" not in err, err
    second = _params(tmp_path / "second.yaml", "mapper", iters_per_keyframe=9)
    with _context("--params-file", first, "--params-file", second) as ctx:
        mapper = MapperNode(context=ctx)
        try:
            assert mapper.config.iters_per_keyframe == 9
        finally:
            mapper.destroy_node()


def test_a_section_for_the_node_that_misses_its_namespace_or_new_name_is_warned_about(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """``mapper:`` is ``/mapper``: under ``-r __ns:=/robot1``, or renamed ``mapper_b``, none of its parameters reached
    the node and nothing said so. Now a warning names the section, the file and the name that would apply; a section
    that names the node in full applies and is not warned about. The map and keyframe topics follow the namespace."""
    params = tmp_path / "p.yaml"
    params.write_text(
        "mapper:\n  ros__parameters:\n    iters_per_keyframe: 5\n"
        "/robot1/mapper:\n  ros__parameters:\n    final_iters: 3\n"
    )
    with _context("--params-file", str(params), "-r", "__ns:=/robot1") as ctx:
        mapper = MapperNode(context=ctx)
        try:
            assert mapper.config.iters_per_keyframe == MapperConfig().iters_per_keyframe
            assert mapper.config.final_iters == 3
            # the data topics follow the namespace (they were absolute: two robots' pipelines shared one map)
            published = {pub.topic_name for pub in mapper.publishers}
            assert {"/robot1/roigsf/map", "/robot1/roigsf/keyframe_poses"} <= published, published
            assert "/robot1/roigsf/keyframe" in {sub.topic_name for sub in mapper.subscriptions}
        finally:
            mapper.destroy_node()
    with _context("--params-file", str(params)) as ctx:
        renamed = MapperNode(context=ctx, node_name="mapper_b")
        renamed.destroy_node()
    err = capfd.readouterr().err
    warnings = [line.split("]: ", 1)[1] for line in err.splitlines() if "does not apply to this node" in line]
    assert warnings == [
        f"section 'mapper' in {params} does not apply to this node, which runs as '/robot1/mapper': its parameters "
        "are not applied (name the section '/robot1/mapper', or '/**/mapper' for any namespace)",
        f"section 'mapper' in {params} does not apply to this node, which runs as '/mapper_b': its parameters are "
        "not applied (name the section '/mapper_b', or '/**/mapper_b' for any namespace)",
    ], err


def test_the_shipped_config_files_reach_namespaced_nodes(capfd: pytest.CaptureFixture[str]) -> None:
    """A walk: the README recommends a namespace per robot, but config/*.yaml and the recommended overlays keyed their
    sections ``mapper:`` (``/mapper``), so under ``-r __ns:=/robot1`` the overlay did nothing but warn. They are keyed
    ``/**/mapper:`` now: any namespace, the plain one too."""
    from roigsf_ros.nodes.nbv_planner import NBVPlannerNode

    config = Path(__file__).resolve().parents[1] / "config"
    files = ("--params-file", str(config / "nbv.yaml"), "--params-file", str(config / "recommended" / "planner.yaml"))
    for ns in ("/robot1", "/"):
        with _context(*files, "-r", f"__ns:={ns}") as ctx:
            planner = NBVPlannerNode(context=ctx, parameter_overrides=[Parameter("warm_up", value=False)])
            try:
                assert planner.nbv.unseen_weight == 2.0 and planner.nbv.unseen_measure == "rays", ns
            finally:
                planner.destroy_node()
    assert "does not apply to this node" not in capfd.readouterr().err


def test_a_namespaced_nodes_parameter_error_names_it_in_full() -> None:
    """A walk: two robots' planners in one launch both said "parameter 'nbv_planner.max_candidates'"; a node under a
    namespace is named in full now, a node without one as before."""
    from roigsf_ros.nodes.nbv_planner import NBVPlannerNode

    for ns, label in (("/robot2", "/robot2/nbv_planner"), ("/", "nbv_planner")):
        with _context("-r", f"__ns:={ns}", "-p", "max_candidates:=0", "-p", "warm_up:=false") as ctx:
            said = _error(lambda ctx=ctx: NBVPlannerNode(context=ctx))
        assert said.startswith(f"parameter '{label}.max_candidates': must be > 0"), said


# ---------------------------------------------------------------------------------------- 3: checked at start-up
@pytest.mark.parametrize(
    ("node", "name", "value", "why"),
    [
        ("mapper", "color_topic", "bad//topic", "must not contain repeated '/'"),
        ("mapper", "keyframe_topic", "1bad", "must not start with a number"),
        ("mapper", "camera_info_topic", "~x//y", "tilde '~' that is not followed by a forward slash"),
        ("nbv_planner", "map_topic", "bad//x", "must not contain repeated '/'"),
        ("keyframe_selector", "color_topic", "bad//topic", "must not contain repeated '/'"),
        ("keyframe_selector", "planner_service", "bad//s", "must not contain repeated '/'"),
    ],
)
def test_an_invalid_topic_or_service_name_is_refused_at_start_up_naming_the_parameter(
    node: str, name: str, value: str, why: str, tmp_path: Path
) -> None:
    """A topic that ROS cannot expand was a traceback (rc 1) when the node made the subscription, and the keyframe
    selector, which subscribes to the camera only after ``startup_wait_s``, started and died 10 s later."""
    from roigsf_ros.nodes.nbv_planner import NBVPlannerNode

    build = {"mapper": MapperNode, "nbv_planner": NBVPlannerNode, "keyframe_selector": KeyframeSelectorNode}[node]
    params = _params(tmp_path / "p.yaml", node, **{name: f"'{value}'"})
    with _context("--params-file", params) as ctx:
        said = _error(lambda: build(context=ctx))
    assert said.startswith(f"parameter '{node}.{name}': '{value}' is no valid ROS name: "), said
    assert why in said and said.endswith(f"(set in {params})"), said


def test_an_input_size_above_the_largest_image_is_refused_at_start_up() -> None:
    """``input_width:=100000`` was accepted; then every frame was dropped with "--width: image size ... is above 8192
    px a side", naming a command-line option the node does not have."""
    from roigsf_ros.nodes.nbv_planner import NBVPlannerNode

    for build in (MapperNode, KeyframeSelectorNode, NBVPlannerNode):
        with _context("-p", "input_width:=100000") as ctx:
            said = _error(lambda b=build: b(context=ctx))
        assert said.endswith(".input_width': must be at most 8192 px, got 100000"), said


def test_a_range_error_names_the_node_and_the_params_file(tmp_path: Path) -> None:
    """``parameter 'max_candidates': must be > 0`` named no node (in active_mapping three nodes share parameter names)
    and, unlike a type error, no params file."""
    from roigsf_ros.nodes.nbv_planner import NBVPlannerNode

    params = _params(tmp_path / "zero.yaml", "nbv_planner", max_candidates=0)
    with _context("--params-file", params) as ctx:
        said = _error(lambda: NBVPlannerNode(context=ctx))
    assert said == f"parameter 'nbv_planner.max_candidates': must be > 0, got 0 (set in {params})", said


def test_ctrl_c_while_a_console_scripts_node_module_imports_is_one_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A Ctrl-C in the first seconds of ``mapper`` (torch and open3d importing) printed an import traceback."""
    from roigsf_ros.nodes import console

    def interrupted(name: str) -> Any:
        raise KeyboardInterrupt

    monkeypatch.setattr(console.importlib, "import_module", interrupted)
    assert console.run("mapper", ["mapper"]) == 130
    assert capsys.readouterr().err == "mapper: interrupted\n"


def test_an_empty_parameter_value_error_shows_how_to_give_one() -> None:
    """``-p load_map:=`` (an empty value) is refused by rcl; the message said only "set as -p NAME:=VALUE", which is
    what the user typed (session 60's walk). It now shows the quoted empty string rcl takes."""
    from rclpy.utilities import remove_ros_args

    from roigsf_ros.nodes.node_process import ROS_ARGS_ERRORS, ros_args_error

    for typed, said in (
        ("load_map:=", "'-p load_map:=': a parameter is set as -p NAME:=VALUE; an empty string is -p \"load_map:=''\""),
        ("load_map", "'-p load_map': a parameter is set as -p NAME:=VALUE"),
    ):
        with pytest.raises(ROS_ARGS_ERRORS) as caught:
            remove_ros_args(["mapper", "--ros-args", "-p", typed])
        assert str(ros_args_error(caught.value)) == said
    assert remove_ros_args(["mapper", "--ros-args", "-p", "load_map:=''"]) == ["mapper"]


def test_a_node_process_says_the_librarys_warnings_through_ros_logging() -> None:
    """Library warnings (a frame without valid depth, a pose outside ``map``) came as bare lines on stderr, without the
    level, time or logger a node's own lines carry, and never reached ``/rosout``: a console script's ``init_ros`` now
    routes them through ROS logging, once each, at WARNING and up as before.
    """
    code = (
        "import logging, rclpy\n"
        "from roigsf_ros.nodes.node_process import init_ros, route_library_logging\n"
        "init_ros(['probe'])\n"
        "assert route_library_logging() is route_library_logging()  # once per process\n"
        "log = logging.getLogger('roigsf_ros.data.bags')\n"
        "log.warning('a library note')\n"
        "log.info('not said at info')\n"
        "rclpy.shutdown()\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if "a library note" in line]
    assert len(lines) == 1 and lines[0].startswith("[WARN]"), proc.stderr
    assert "[roigsf_ros.data.bags]: a library note" in lines[0], lines
    assert "not said at info" not in proc.stderr + proc.stdout
