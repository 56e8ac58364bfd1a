"""config/*.yaml carry exactly the Python API's defaults, under the same names (config over constants)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import yaml

from roigsf_ros.mapping import MapperConfig
from roigsf_ros.nbv import NBVConfig

CONFIG = Path(__file__).resolve().parents[1] / "config"


@pytest.mark.parametrize(
    ("file", "node", "cls"), [("mapper.yaml", "mapper", MapperConfig), ("nbv.yaml", "nbv_planner", NBVConfig)]
)
def test_yaml_defaults_equal_dataclass_defaults(file: str, node: str, cls: type) -> None:
    params = yaml.safe_load((CONFIG / file).read_text())[node]["ros__parameters"]
    defaults = {f.name: getattr(cls(), f.name) for f in dataclasses.fields(cls)}
    assert set(params) == set(defaults)
    for name, value in defaults.items():
        assert params[name] == (list(value) if isinstance(value, tuple) else value), name
