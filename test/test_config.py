"""config/*.yaml carry exactly the Python API's defaults, under the same names (config over constants)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import yaml

from roigsf_ros.core.config import Config
from roigsf_ros.mapping.mapper import MapperConfig
from roigsf_ros.nbv.config import NBVConfig

CONFIG = Path(__file__).resolve().parents[1] / "config"


@pytest.mark.parametrize(
    ("file", "node", "cls"), [("mapper.yaml", "mapper", MapperConfig), ("nbv.yaml", "nbv_planner", NBVConfig)]
)
def test_yaml_defaults_equal_dataclass_defaults(file: str, node: str, cls: type) -> None:
    params = yaml.safe_load((CONFIG / file).read_text())[f"/**/{node}"]["ros__parameters"]
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
        params = yaml.safe_load((CONFIG / file).read_text())[f"/**/{node.get_name()}"]["ros__parameters"]
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


DEFAULT_FILES = {"mapper": "mapper.yaml", "nbv_planner": "nbv.yaml", "keyframe_selector": "keyframe_selector.yaml"}
"""Each node's config file of defaults (the overlays in config/recommended/ change a few of them)."""


def _overlay(name: str) -> dict[str, dict[str, object]]:
    """config/recommended/``name``: {node: {parameter: value}} (its sections ``/**/node``: in any namespace)."""
    text = (CONFIG / "recommended" / name).read_text()
    return {node.removeprefix("/**/"): body["ros__parameters"] for node, body in yaml.safe_load(text).items()}


def test_recommended_overlays_change_declared_parameters_with_values_of_their_type() -> None:
    """Each overlay names only parameters of its nodes' config files, each with a value of the default's type (a ROS
    node refuses ``2`` for a double parameter) that differs from the default: an overlay is what it changes (and the
    selector's policy, which the stream overlay names so that the file says what it runs)."""
    files = sorted((CONFIG / "recommended").glob("*.yaml"))
    assert [f.name for f in files] == ["planner.yaml", "stream.yaml"]
    for file in files:
        for node, params in _overlay(file.name).items():
            defaults = yaml.safe_load((CONFIG / DEFAULT_FILES[node]).read_text())[f"/**/{node}"]["ros__parameters"]
            for name, value in params.items():
                assert name in defaults, f"{file.name}: {node} has no parameter {name}"
                assert type(value) is type(defaults[name]), f"{file.name}: {node}.{name}: {value!r}"
                assert value != defaults[name] or name == "policy", f"{file.name}: {node}.{name} is the default"


def test_the_recommended_overlays_are_the_library_recommendations() -> None:
    """config/recommended/planner.yaml is ``RECOMMENDED_UNSEEN``; stream.yaml is the stream variant's policy and
    parameters (the planner's share, the NBVConfig fields, on the planner) and its mapper setting."""
    from roigsf_ros.nbv.config import RECOMMENDED_UNSEEN
    from roigsf_ros.policies import RECOMMENDED_STREAM, RECOMMENDED_STREAM_MAPPER, RECOMMENDED_STREAM_POLICY

    assert _overlay("planner.yaml") == {"nbv_planner": dict(RECOMMENDED_UNSEEN)}
    scorer = {f.name for f in dataclasses.fields(NBVConfig)}
    selector = {k: v for k, v in RECOMMENDED_STREAM.items() if k not in scorer}
    assert _overlay("stream.yaml") == {
        "keyframe_selector": {"policy": RECOMMENDED_STREAM_POLICY, **selector},
        "nbv_planner": {k: v for k, v in RECOMMENDED_STREAM.items() if k in scorer},
        "mapper": dict(RECOMMENDED_STREAM_MAPPER),
    }


def test_changed_names_the_fields_off_their_defaults() -> None:
    """``Config.changed``: what a node's start-up line lists."""
    from roigsf_ros.nbv.config import RECOMMENDED_UNSEEN

    assert NBVConfig().changed() == {} and MapperConfig().changed() == {}
    assert NBVConfig(**RECOMMENDED_UNSEEN).changed() == dict(RECOMMENDED_UNSEEN)
    assert MapperConfig(init_max_stretch=4.0, iters_per_keyframe=10).changed() == {"init_max_stretch": 4.0}

    @dataclasses.dataclass(frozen=True)
    class Run(Config):  # as BenchConfig: a required field, a nested config by default_factory
        scene: str
        seeds: int = 1
        mapper: MapperConfig = dataclasses.field(default_factory=MapperConfig)

    assert Run("s", 3).changed() == {"seeds": 3}  # a required field has no default to differ from
    assert Run("s", mapper=MapperConfig(init_max_stretch=4.0)).changed()["mapper"]["init_max_stretch"] == 4.0


def test_configs_and_policies_refuse_a_value_of_the_wrong_type_by_its_field() -> None:
    """A word, or a bool, where a number belongs is refused on construction naming the field (it once reached
    ``int('abc')`` or a comparison of str and float, a traceback naming nothing); numpy scalars and a whole float for
    an int pass, as values read from arrays and JSON do.
    """
    import numpy as np

    from roigsf_ros.core.errors import InputError
    from roigsf_ros.experiments.pool import PoolConfig
    from roigsf_ros.policies.base import make_policy

    for cls, name, bad, words in [
        (MapperConfig, "iters_per_keyframe", "x", "a whole number"),
        (MapperConfig, "iters_per_keyframe", True, "a whole number"),
        (MapperConfig, "iters_per_keyframe", 2.5, "a whole number"),
        (NBVConfig, "unseen_alpha", "x", "a number"),  # was: '<' not supported between 'float' and 'str'
        (NBVConfig, "top_k", "x", "a whole number"),  # was: invalid literal for int()
        (PoolConfig, "n_views", "20", "a whole number"),
    ]:
        with pytest.raises(InputError, match=f"^{name}: must be {words}, got {bad!r}$"):
            cls(**{name: bad})
    assert MapperConfig(iters_per_keyframe=np.int64(3), near_m=np.float32(0.25)).iters_per_keyframe == 3
    assert MapperConfig(iters_per_keyframe=4.0).iters_per_keyframe == 4.0
    assert NBVConfig(unseen_bbox_margin_m=np.inf).unseen_bbox_margin_m == np.inf
    for name, params, field in [
        ("roi-gsurfisher", {"window": "abc"}, "window"),  # was: invalid literal for int()
        ("roi-gsurfisher", {"adaptive_ratio": "abc"}, "adaptive_ratio"),  # was: ufunc 'isfinite' not supported
        ("random", {"seed": True}, "seed"),  # was: silently seed 1
        ("every-n", {"n": "x"}, "n"),
        ("gaus-slam", {"tau_k": "x"}, "tau_k"),
        ("roi-gsurfisher", {"voxel_size_m": "x"}, "voxel_size_m"),  # was: accepted, failing at the first window
    ]:
        with pytest.raises(InputError, match=f"^{field}: must be "):
            make_policy(name, **params)
    with pytest.raises(InputError, match=r"^voxel_size_m: must be a finite number > 0 \(m\), got -1$"):
        make_policy("roi-gsurfisher", voxel_size_m=-1)
    with pytest.raises(InputError, match=r"^policy 'roi-gsurfisher': takes no parameter"):
        make_policy("roi-gsurfisher", windw=3)
    assert make_policy("roi-gsurfisher", window=12.0, seed=np.int64(2)).window == 12


def test_a_policy_built_directly_checks_its_arguments_as_make_policy_does() -> None:
    """The Python API builds policies by class too: a word for a number is refused by the constructor itself, naming
    the parameter, given by keyword or by position (it once failed inside the constructor, naming nothing, while
    make_policy refused it); subclasses with their own ``__init__`` are checked as well.
    """
    import numpy as np

    from roigsf_ros.core.errors import InputError
    from roigsf_ros.policies.rules import EveryN, GausSlam
    from roigsf_ros.policies.stream import StreamNBVPolicy

    for build, field in [
        (lambda: StreamNBVPolicy(window="abc"), "window"),  # was: '<' not supported between 'str' and 'int'
        (lambda: StreamNBVPolicy(adaptive_ratio="abc"), "adaptive_ratio"),
        (lambda: StreamNBVPolicy(seed=True), "seed"),
        (lambda: EveryN("5"), "n"),  # by position
        (lambda: GausSlam(tau_k="x"), "tau_k"),
    ]:
        with pytest.raises(InputError, match=f"^{field}: must be "):
            build()
    assert StreamNBVPolicy(window=np.int64(6)).window == 6
    assert EveryN(3).n == 3

    class Hinted(EveryN):  # an annotation named for type checking only stays unchecked, not a NameError
        def __init__(self, n: int = 5, clock: NotImportedHere | None = None) -> None:  # noqa: F821
            super().__init__(n)

    assert Hinted(4, clock=object()).n == 4
    with pytest.raises(InputError, match=r"^n: must be a whole number"):
        Hinted("4")  # the parent's check still runs


def test_a_misspelt_field_names_the_closest_one() -> None:
    """``NBVConfig(unseen_wieght=2)`` was Python's bare "unexpected keyword argument": now the config and the closest
    field are named (still a TypeError, as Python's own), and a name close to none lists the fields."""
    from roigsf_ros.core.config import UnknownFieldError

    with pytest.raises(TypeError, match=r"^NBVConfig: no field unseen_wieght \(did you mean unseen_weight\?\)$"):
        NBVConfig(unseen_wieght=2.0)
    with pytest.raises(UnknownFieldError, match=r"^MapperConfig: no field zzz; its fields: iters_per_keyframe, "):
        MapperConfig(zzz=1)
    assert NBVConfig(unseen_weight=2.0).unseen_weight == 2.0
