"""The launch files, run against stand-ins for ``launch`` and ``launch_ros`` (not on PyPI, so not installed here).

What they hand to ``launch_ros``: executables that exist, params files that exist, parameter names the node
declares, the player's rate as a float and, for three processes, a player that waits for both camera nodes.
"""

from __future__ import annotations

import importlib.util
import re
import sys
import types
from pathlib import Path
from typing import Any

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
LAUNCH_FILES = sorted((REPO / "launch").glob("*.launch.py"))


class _Recorded:
    """A stand-in for a launch class: keeps its arguments."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.args, self.kwargs = args, kwargs


class Node(_Recorded):
    pass


class ParameterValue(_Recorded):
    pass


class LaunchConfiguration(_Recorded):
    pass


class NotEqualsSubstitution(_Recorded):
    pass


def _stub_modules(monkeypatch: pytest.MonkeyPatch) -> None:
    """``launch``, ``launch_ros`` and the ament index as modules of stand-ins."""
    config = REPO / "config"
    stubs = {
        "launch": {"LaunchDescription": lambda entities: list(entities)},
        "launch.actions": {"DeclareLaunchArgument": _Recorded},
        "launch.conditions": {"IfCondition": _Recorded},
        "launch.substitutions": {
            "LaunchConfiguration": LaunchConfiguration,
            "NotEqualsSubstitution": NotEqualsSubstitution,
        },
        "launch_ros": {},
        "launch_ros.actions": {"Node": Node},
        "launch_ros.parameter_descriptions": {"ParameterValue": ParameterValue},
        "ament_index_python": {},
        "ament_index_python.packages": {"get_package_share_directory": lambda name: str(config.parent)},
    }
    for name, attrs in stubs.items():
        module = types.ModuleType(name)
        module.__dict__.update(attrs)
        monkeypatch.setitem(sys.modules, name, module)


def _nodes(path: Path, monkeypatch: pytest.MonkeyPatch) -> list[Node]:
    _stub_modules(monkeypatch)
    spec = importlib.util.spec_from_file_location(path.stem.replace(".", "_"), path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return [e for e in module.generate_launch_description() if isinstance(e, Node)]


NO_DEFAULT = {"bag_player": {"bag"}}
"""Parameters a node declares that its config file leaves out: it refuses to start without them."""


def _declared(executable: str) -> set[str]:
    """The parameter names of an executable's nodes, from their config files."""
    names = {"active_mapping": ("mapper", "nbv", "keyframe_selector"), "nbv_planner": ("nbv",)}.get(
        executable, (executable,)
    )
    declared = set(NO_DEFAULT.get(executable, ()))
    for name in names:
        for section in yaml.safe_load((REPO / "config" / f"{name}.yaml").read_text()).values():
            declared |= set(section["ros__parameters"])
    return declared


def _console_scripts() -> set[str]:
    return set(re.findall(r'"(\w+) = roigsf_ros\.', (REPO / "setup.py").read_text()))


@pytest.mark.parametrize("path", LAUNCH_FILES, ids=lambda p: p.name)
def test_launch_file_names_what_exists(path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    nodes = _nodes(path, monkeypatch)
    assert nodes
    for node in nodes:
        executable = node.kwargs["executable"]
        assert node.kwargs["package"] == "roigsf_ros" and executable in _console_scripts()
        for entry in node.kwargs["parameters"]:
            if isinstance(entry, str):
                assert Path(entry).is_file(), entry
            else:
                assert set(entry) <= _declared(executable), (executable, set(entry) - _declared(executable))


@pytest.mark.parametrize("path", LAUNCH_FILES, ids=lambda p: p.name)
def test_launch_file_player_takes_rate_as_float_and_waits_for_both_camera_nodes(
    path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``rate:=1`` reached the player as an integer, which its float parameter refuses; with three processes the
    player started on the first camera node to match (its file's ``wait_for_subscribers: 1``), and the other
    missed the first frames (the README gives that command ``wait_for_subscribers:=2``)."""
    nodes = _nodes(path, monkeypatch)
    (player,) = [n for n in nodes if n.kwargs["executable"] == "bag_player"]
    given = {k: v for entry in player.kwargs["parameters"] if isinstance(entry, dict) for k, v in entry.items()}
    rate = given["rate"]
    assert isinstance(rate, ParameterValue) and rate.kwargs.get("value_type") is float
    camera_nodes = [n for n in nodes if n.kwargs["executable"] in ("mapper", "keyframe_selector")]
    if camera_nodes:  # three processes: and the README's 30 s for three processes importing torch and open3d at once
        assert given.get("wait_for_subscribers") == len(camera_nodes) == 2 and given.get("wait_timeout_s") == 30.0
    # played only when a bag is given, compared as a value: a PythonExpression pasting the path between quotes broke
    # on a path with a quote in it
    (condition,) = player.kwargs["condition"].args
    assert isinstance(condition, NotEqualsSubstitution) and condition.args[1] == "", condition
