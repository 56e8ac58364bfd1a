"""config/*.yaml carry exactly the Python API's defaults, under the same names (config over constants)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import yaml

from roigsf_ros.mapping.mapper import MapperConfig
from roigsf_ros.nbv.config import NBVConfig

CONFIG = Path(__file__).resolve().parents[1] / "config"


@pytest.mark.parametrize(
    ("file", "node", "cls"), [("mapper.yaml", "mapper", MapperConfig), ("nbv.yaml", "nbv_planner", NBVConfig)]
)
def test_yaml_defaults_equal_dataclass_defaults(file: str, node: str, cls: type) -> None:
    params = yaml.safe_load((CONFIG / file).read_text())[node]["ros__parameters"]
    defaults = {f.name: getattr(cls(), f.name) for f in dataclasses.fields(cls)}
    assert set(defaults) <= set(params)  # the rest are the node's own parameters (next test)
    for name, value in defaults.items():
        assert params[name] == (list(value) if isinstance(value, tuple) else value), name


@pytest.mark.parametrize(
    ("file", "module", "cls_name"),
    [
        ("mapper.yaml", "roigsf_ros.nodes.mapper", "MapperNode"),
        ("nbv.yaml", "roigsf_ros.nodes.nbv_planner", "NBVPlannerNode"),
        ("keyframe_selector.yaml", "roigsf_ros.nodes.keyframe_selector", "KeyframeSelectorNode"),
    ],
)
def test_yaml_equals_node_parameter_defaults(file: str, module: str, cls_name: str, ros_context: object) -> None:
    """Every parameter a node declares is in its config file with the declared default, and nothing else is."""
    pytest.importorskip("roigsf_interfaces")
    import importlib

    node_cls = getattr(importlib.import_module(module), cls_name)
    node = node_cls(context=ros_context)
    try:
        params = yaml.safe_load((CONFIG / file).read_text())[node.get_name()]["ros__parameters"]
        declared = {
            name: node.get_parameter(name).value
            for name in node._parameters
            if name not in ("use_sim_time", "start_type_description_service")
        }
    finally:
        node.destroy_node()
    assert set(params) == set(declared)
    for name, value in declared.items():
        assert params[name] == (list(value) if isinstance(value, tuple | list) else value), name
