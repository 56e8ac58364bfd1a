"""Parameters of the roigsf nodes: declared up front, checked, and their errors naming the params file.

A method config dataclass (MapperConfig, NBVConfig) becomes one ROS parameter per field with the
same name and default (its attribute docstring as the description), so ``--ros-args -p`` and
``--params-file`` reach every tunable. How a node process starts, spins and stops is :mod:`node_process`.
"""

from __future__ import annotations

import ast
import dataclasses
import difflib
import functools
import inspect
import itertools
import math
import re
import textwrap
import weakref
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    InvalidServiceNameException,
    InvalidTopicNameException,
)
from rclpy.expand_topic_name import expand_topic_name
from rclpy.node import Node
from rclpy.validate_full_topic_name import validate_full_topic_name

from roigsf_ros.core.camera import MAX_IMAGE_SIDE
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.package_files import package_path

if TYPE_CHECKING:
    from rclpy.context import Context
    from rclpy.parameter import Parameter

    from roigsf_ros.nodes.shared_map import SharedMapper

BAD_PARAMETER_ERRORS = (InputError, InvalidParameterTypeException, InvalidParameterValueException, ValueError)
"""Exceptions a node constructor raises for a bad parameter value (reported, exit code 2)."""


@functools.cache
def field_docs(cls: type) -> dict[str, str]:
    """The attribute docstrings of a dataclass's fields (first sentence), read from its source."""
    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    except (OSError, TypeError, SyntaxError):
        return {}
    body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
    docs: dict[str, str] = {}
    for prev, node in itertools.pairwise(body):
        if (
            isinstance(prev, ast.AnnAssign)
            and isinstance(prev.target, ast.Name)
            and isinstance(node, ast.Expr)
            and isinstance(node.value, ast.Constant)
            and isinstance(node.value.value, str)
        ):
            docs[prev.target.id] = " ".join(node.value.value.split())
    return docs


_KIND_WORDS = {int: "an int", float: "a float", str: "a string", bool: "a bool", list: "a list"}
"""How :func:`declare`'s error names a parameter's type."""

_RCL_TYPE_WORDS = {
    "BOOL": "a bool",
    "INTEGER": "an int",
    "DOUBLE": "a float",
    "STRING": "a string",
    "BYTE_ARRAY": "a list of bytes",
    "BOOL_ARRAY": "a list of bools",
    "INTEGER_ARRAY": "a list of ints",
    "DOUBLE_ARRAY": "a list of floats",
    "STRING_ARRAY": "a list of strings",
}
"""How an error names a parameter type of rclpy's messages (``expecting type 'DOUBLE'``)."""


def _notes(*notes: str) -> str:
    """`` (a; b)`` from the non-empty ``notes``, "" when there are none: the remarks after an error's value."""
    kept = [n for n in notes if n]
    return f" ({'; '.join(kept)})" if kept else ""


def _set_in(node: Node, name: str) -> str:
    """``"set in FILE"`` for a parameter of ``node`` a params file set, else ""."""
    source = parameter_source(node, name)
    return f"set in {source}" if source not in (None, "-p") else ""


def _float_hint(name: str, given: Any, source: str | None) -> str:
    """The advice for an int given to a float parameter (``write a float with a point, e.g. 1.0``), with ``-p``'s
    syntax when the value came from ``-p``.
    """
    example = f"{float(given)!r}"
    return f"write a float with a point, e.g. {f'-p {name}:={example}' if source == '-p' else example}"


def node_label(node: Node) -> str:
    """How a parameter error names its node: ``nbv_planner``, or ``/robot2/nbv_planner`` under a namespace (two
    robots' planners read alike in one launch's log).
    """
    return node.get_name() if node.get_namespace() == "/" else node.get_fully_qualified_name()


def _type_error(node: Node, name: str, default: Any) -> InputError:
    """The InputError for an override of ``name`` whose type is not that of its ``default``: the value given, the
    params file it came from, and the float hint only for an int given to a float parameter.
    """
    override = getattr(node, "_parameter_overrides", {}).get(name)
    given = None if override is None else override.value
    source = parameter_source(node, name)
    int_for_float = isinstance(default, float) and isinstance(given, int) and not isinstance(given, bool)
    kind = _KIND_WORDS.get(type(default), f"a {type(default).__name__}")
    problem = f"must be {kind} like its default {default!r}" + ("" if override is None else f", got {given!r}")
    file_note = f"set in {source}" if source not in (None, "-p") else ""
    problem += _notes(file_note, _float_hint(name, given, source) if int_for_float else "")
    return InputError(f"parameter '{node_label(node)}.{name}'", problem)


def declare(node: Node, name: str, default: Any, description: str) -> Any:
    """Declare one parameter with a default and a description; returns its (possibly overridden) value.

    Read-only (:data:`READ_AT_START`): the nodes read their parameters once, at start-up, so a change at run time
    (``ros2 param set``) is refused saying so, where it was accepted and then ignored. A ``*_topic`` or ``*_service``
    parameter's name is checked and returned as ROS expands it (:func:`check_ros_name`): ``roigsf/map`` is
    ``/robot1/roigsf/map`` under ``-r __ns:=/robot1``, and the logs say so.
    """
    value = list(default) if isinstance(default, tuple) else default
    node.__dict__.setdefault("_roigsf_defaults", {})[name] = value  # changed_parameters
    try:
        got = node.declare_parameter(name, value, read_at_start(description)).value
    except InvalidParameterTypeException:  # e.g. `-p near_m:=0`: an int where the default is a float
        raise _type_error(node, name, default) from None
    if (conflict := overlay_type_conflict(node, name)) is not None:
        raise conflict
    if isinstance(got, str) and got and name.endswith(("_topic", "_service")):
        return check_ros_name(node, name, got)  # in full: a relative default follows the node's namespace
    return got


READ_AT_START = "read at start-up: set it with -p NAME:=VALUE or a params file, and restart the node"
"""What a parameter's description ends with: every parameter of the package's nodes is read-only once declared."""


def read_at_start(description: str) -> ParameterDescriptor:
    """The read-only descriptor of a parameter the node reads once, at start-up (:func:`declare`)."""
    return ParameterDescriptor(description=f"{description} ({READ_AT_START})", read_only=True)


def check_ros_name(node: Node, name: str, value: str) -> str:
    """``value`` (a topic or service name, given as parameter ``name``) expanded for ``node``; an InputError naming
    the parameter (and its params file) when ROS would refuse it: at start-up, not as a traceback when the
    subscription is made (the keyframe selector makes its camera subscriptions only after ``startup_wait_s``).
    """
    try:
        full = expand_topic_name(value, node.get_name(), node.get_namespace())
        validate_full_topic_name(full, is_service=name.endswith("_service"))
    except (InvalidTopicNameException, InvalidServiceNameException, ValueError) as exc:
        why = str(exc).split(", at /")[0].split("\n")[0].rstrip(":")  # rcl's source location; the caret lines
        why = re.sub(r"^(Invalid (topic|service) name: |topic name '.*' is invalid: )", "", why)
        why += _notes(_set_in(node, name))
        raise InputError(f"parameter '{node_label(node)}.{name}'", f"{value!r} is no valid ROS name: {why}") from None
    return full


def _config_error(node: Node, values: dict[str, Any], exc: InputError) -> InputError:
    """A config class's InputError for the parameters ``values`` as a parameter error of ``node``: its field as
    ``parameter 'node.field'``, with the params file that set the value.
    """
    field = exc.where.rsplit(".", 1)[-1]
    if field not in values:
        return exc
    problem = exc.problem + _notes(_set_in(node, field))
    return InputError(f"parameter '{node_label(node)}.{field}'", problem)


def declare_config(node: Node, cls: type, skip: Iterable[str] = ()) -> dict[str, Any]:
    """Declare every field of the dataclass ``cls`` as a parameter (default = the field's); returns name -> value.

    Arrays come back as tuples, as the dataclasses hold them. Without ``skip`` the values are checked by building
    ``cls`` from them: its InputError (which says the allowed range) names the parameter and its params file.
    """
    docs = field_docs(cls)
    defaults = cls()
    skip = set(skip)
    out: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        if f.name in skip:
            continue
        value = declare(node, f.name, getattr(defaults, f.name), docs.get(f.name, f"{cls.__name__}.{f.name}"))
        out[f.name] = tuple(value) if isinstance(value, list | tuple) else value
    if not skip:  # checked here, where the error can name the node, the allowed range and the params file
        try:
            cls(**out)
        except InputError as exc:
            raise _config_error(node, out, exc) from None
    return out


RCLPY_PARAMETERS = frozenset({"use_sim_time", "start_type_description_service"})
"""Parameters rclpy itself reads (declared by it on demand): overrides of them are never a node's typo."""

RCLPY_PARAMETER_PREFIXES = ("qos_overrides.",)
"""Prefixes of rclpy's own parameters (QoS overrides of a topic, declared only where a node allows them)."""


def _declared_names(node: Node) -> list[str]:
    """The parameters ``node`` declared, rclpy's own left out: the names a typo is matched against."""
    return [n for n in node.list_parameters([], 0).names if n not in RCLPY_PARAMETERS]


def _closest(name: str, declared: Iterable[str]) -> list[str]:
    """The declared names closest to an unknown parameter ``name`` (at most 3, none when nothing is close)."""
    return difflib.get_close_matches(name, list(declared), n=3, cutoff=0.75)


def _hint(name: str, declared: Iterable[str]) -> str:
    """`` (closest declared: a, b)`` after an unknown parameter ``name``, or "" when no declared name is close."""
    close = _closest(name, declared)
    return f" (closest declared: {', '.join(close)})" if close else ""


PACKAGE_CONFIG_FILES = ("mapper.yaml", "nbv.yaml", "keyframe_selector.yaml", "bag_player.yaml")
"""The params files of the package's nodes (config/): every parameter each node declares, with its default."""

ROIGSF_NODE_NAMES = ("mapper", "nbv_planner", "keyframe_selector", "bag_player")
"""The default names of the package's nodes: a params file's section for one of them is no typo of another's."""


def package_config_folder() -> Path | None:
    """The folder with the package's params files (:func:`~roigsf_ros.core.package_files.package_path`: the
    checkout's config/, else the installed one); None when none holds them all.
    """
    return package_path("config", lambda folder: all((folder / name).is_file() for name in PACKAGE_CONFIG_FILES))


@functools.cache
def package_parameter_names() -> frozenset[str]:
    """Every parameter some node of this package declares, read from its params files (:func:`package_config_folder`);
    empty when none is found.

    A ``-p NAME:=VALUE`` reaches every node of a process, and the README gives the three processes the same camera
    arguments: a name another node of the package declares is not a typo in a node that runs on its own.
    """
    folder = package_config_folder()
    if folder is None:
        return frozenset()
    return frozenset(key for name in PACKAGE_CONFIG_FILES for *_, params in params_file_sections(folder / name)
                     for key in params)  # fmt: skip


_ROS_ARGS: weakref.WeakKeyDictionary[Context, tuple[str, ...]] = weakref.WeakKeyDictionary()
"""The arguments each context was initialised with (:func:`remember_ros_args`); rclpy keeps no copy of them."""

_ROS_ARG_VALUE_FLAGS = frozenset(
    {"-r", "--remap", "-e", "--enclave", "--log-level", "--log-config-file", "--log-file-name"}
)
"""ROS arguments (besides ``-p`` and ``--params-file``) that take the next argument as their value."""


def remember_ros_args(context: Context, args: Sequence[str]) -> None:
    """Note the arguments ``context`` was initialised with (:func:`init_ros` does for the console scripts): the
    params files that a node's parameter errors and its misspelt-section warnings name.
    """
    _ROS_ARGS[context] = tuple(args)


def context_with_params_files(params_files: Sequence[Path], domain_id: int | None) -> Context:
    """A fresh rclpy context with the params files in order (later ones win, as ROS reads them), its arguments noted
    (:func:`remember_ros_args`): nodes made in it then warn of a misspelt section (``mappr:``) and a bad value's error
    says ``(set in FILE)``, as with ``--ros-args --params-file FILE``.
    """
    import rclpy

    args = None
    if params_files:
        args = ["roigsf", "--ros-args", *(a for f in params_files for a in ("--params-file", str(f)))]
    context = rclpy.Context()
    rclpy.init(args=args, context=context, domain_id=domain_id)
    if args is not None:
        remember_ros_args(context, args)
    return context


def ros_parameter_rules(context: Context) -> list[tuple[str, str]]:
    """The parameter sources in ``context``'s ROS arguments, in order (a later one wins): ``("file", PATH)`` for a
    ``--params-file``, ``("-p", RULE)`` for a ``-p RULE``; empty when its arguments were not noted.
    """
    rules: list[tuple[str, str]] = []
    in_ros = False
    args = iter(_ROS_ARGS.get(context, ()))
    for arg in args:
        if arg in ("--ros-args", "--"):
            in_ros = arg == "--ros-args"
        elif in_ros and arg in ("-p", "--param", "--params-file"):
            value = next(args, None)
            if value is not None:
                rules.append(("file" if arg == "--params-file" else "-p", value))
        elif in_ros and arg in _ROS_ARG_VALUE_FLAGS:
            next(args, None)
    return rules


def params_file_sections(path: str | Path, strict: bool = False) -> list[tuple[str, str, dict[str, Any]]]:
    """The node sections of a params file as ``(label, pattern, parameters)``: the label as written (``mappr``,
    ``/ns/mapper``), the node pattern (``/mappr``, ``/**``), the parameters with nested names dotted.

    A file that is not a ROS params file (a YAML mapping of node names, or namespaces of them, to
    ``ros__parameters`` mappings) gives what could be read (empty when nothing), or with ``strict`` an InputError
    naming the file and the entry (rclpy's own error on a bad file names neither).
    """
    import yaml

    where = Path(path)
    try:
        data = yaml.safe_load(where.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError, UnicodeDecodeError) as exc:
        if not strict:
            return []
        if isinstance(exc, FileNotFoundError):
            raise InputError(where, "params file not found") from None
        raise InputError(where, f"not a readable YAML params file ({exc})") from None
    if strict and (not isinstance(data, dict) or not data):
        raise InputError(where, "a params file maps node names to {ros__parameters: {...}}")

    def flat(values: dict[str, Any], prefix: str = "") -> dict[str, Any]:
        out: dict[str, Any] = {}
        for key, value in values.items():
            out.update(flat(value, f"{prefix}{key}.") if isinstance(value, dict) else {f"{prefix}{key}": value})
        return out

    sections: list[tuple[str, str, dict[str, Any]]] = []

    def walk(values: dict[Any, Any], label: str, pattern: str) -> None:
        for key, value in values.items():
            here, below = f"{label}/{key}" if label else str(key), f"{pattern}/{str(key).strip('/')}"
            if isinstance(value, dict) and "ros__parameters" in value:
                if isinstance(value["ros__parameters"], dict):
                    sections.append((here, below, flat(value["ros__parameters"])))
                    continue
                if strict:
                    raise InputError(where, f"{here!r}: 'ros__parameters' is not a mapping")
            if not isinstance(value, dict) or not value:
                if strict:
                    raise InputError(where, f"{here!r}: needs a 'ros__parameters' mapping")
                continue
            walk(value, here, below)  # the nested form: a namespace, then the node

    if isinstance(data, dict):
        walk(data, "", "")
    return sections


def _applies(pattern: str, fully_qualified_name: str) -> bool:
    """Whether a params file's node pattern (``/mapper``, ``/**``, ``/*/mapper``) names the node, as rcl matches it."""
    regex = ""
    for token in pattern.strip("/").split("/"):
        regex += "(?:/[^/]+)*" if token == "**" else "/" + re.escape(token).replace(r"\*", "[^/]*")
    return re.fullmatch(regex, fully_qualified_name) is not None


def _same_value(a: Any, b: Any) -> bool:
    """Whether two parameter values are the same value of the same type (``1`` is not ``1.0``; nan is nan)."""
    if isinstance(a, list | tuple) or isinstance(b, list | tuple) or type(a).__name__ == "array":
        try:
            return len(a) == len(b) and all(_same_value(x, y) for x, y in zip(a, b, strict=True))
        except TypeError:
            return False
    if type(a) is not type(b):
        return False
    return a == b or (isinstance(a, float) and math.isnan(a) and math.isnan(b))


def parameter_source(node: Node, name: str) -> str | None:
    """Where ``node``'s override of ``name`` came from: the params file's path as given, ``"-p"``, or None when not
    known (no override, arguments not noted by :func:`remember_ros_args`, or a constructor override in its place).
    """
    override = getattr(node, "_parameter_overrides", {}).get(name)
    if override is None:
        return None
    found = _rule_values(node).get(name, [])
    return found[-1][0] if found and _same_value(found[-1][1], override.value) else None


def _rule_values(node: Node) -> dict[str, list[tuple[str, Any]]]:
    """Every value ``node``'s ROS arguments give each parameter (its params files' sections that apply to it, ``-p``),
    in order, as ``{name: [(params file path or "-p", value as YAML reads it), ...]}``: the last one is meant to win.
    Each params file is read once per node: the result is kept on the node (its arguments do not change).
    """
    import yaml

    cached = getattr(node, "_roigsf_rule_values", None)
    if cached is not None:
        return cached
    fqn = node.get_fully_qualified_name()
    found: dict[str, list[tuple[str, Any]]] = {}
    for kind, arg in ros_parameter_rules(node.context):
        if kind == "file":
            for _, pattern, params in params_file_sections(arg):
                if _applies(pattern, fqn):
                    for name, value in params.items():
                        found.setdefault(name, []).append((arg, value))
            continue
        target, _, value = arg.partition(":=")
        who, _, name = target.rpartition(":")
        if not who or _applies(who, fqn):
            try:
                found.setdefault(name, []).append(("-p", yaml.safe_load(value)))
            except yaml.YAMLError:
                found.setdefault(name, []).append(("-p", value))
    node._roigsf_rule_values = found  # type: ignore[attr-defined]
    return found


def _reads_as_number(value: Any) -> bool:
    """Whether a string YAML 1.1 left unparsed is a number to rcl's parser too (``1e3``), so not a type change."""
    try:
        float(value)
    except (TypeError, ValueError):
        return False
    return isinstance(value, str)


def overlay_type_conflict(node: Node, name: str) -> InputError | None:
    """The InputError for parameter ``name`` of ``node`` when its last params file gives a value of another type than
    an earlier file's, else None: rcl then keeps the earlier value without a word (``--params-file config/nbv.yaml
    --params-file mine.yaml`` with ``unseen_weight: "2.0"`` in mine.yaml ran on nbv.yaml's 0.0), where the same file
    alone is refused. :func:`declare` asks as it declares, so the node refuses before its start-up work and log line.
    """
    override = getattr(node, "_parameter_overrides", {}).get(name)
    if override is None:
        return None
    found = _rule_values(node).get(name, [])
    if len(found) < 2 or found[-1][0] == "-p" or _same_value(found[-1][1], override.value):
        return None
    source, value = found[-1]
    kept = [src for src, v in found[:-1] if src != "-p" and _same_value(v, override.value)]
    if not kept or type(value) is type(override.value) or _reads_as_number(value):
        return None
    kind = _KIND_WORDS.get(type(override.value), f"a {type(override.value).__name__}")
    return InputError(
        f"parameter '{node_label(node)}.{name}'",
        f"must be {kind}, got {value!r} (set in {source}; ROS kept {override.value!r} from {kept[-1]} instead, "
        "as a later params file cannot change the type of a value an earlier one set)",
    )


def overlay_type_conflicts(node: Node) -> list[InputError]:
    """:func:`overlay_type_conflict` for every declared parameter of ``node`` that has an override (a node that
    declares some parameters without :func:`declare`).
    """
    overrides = getattr(node, "_parameter_overrides", {})
    found = (overlay_type_conflict(node, name) for name in overrides if node.has_parameter(name))
    return [error for error in found if error is not None]


def parameter_error(node: Node | None, exc: BaseException) -> BaseException:
    """``exc`` as the nodes report a bad parameter: rclpy's type and range errors as an InputError in
    :func:`declare`'s words (the range said), and a ``parameter 'NAME'`` InputError of ``node`` as ``'node.NAME'``
    with the params file that set the value; anything else as it is. Call it while ``node`` still exists.
    """
    name_of = "" if node is None else f"{node_label(node)}."
    text = str(exc)
    if isinstance(exc, InvalidParameterTypeException) and (m := _RCLPY_TYPE_ERROR.search(text)):
        given = repr(m["value"]) if m["given"] == "STRING" else m["value"]
        hint = _float_hint(m["name"], float(m["value"]), None) if m["given"] + m["want"] == "INTEGERDOUBLE" else ""
        want = _RCL_TYPE_WORDS.get(m["want"], m["want"].lower())
        return InputError(f"parameter '{name_of}{m['name']}'", f"must be {want}, got {given}{_notes(hint)}")
    if isinstance(exc, InvalidParameterValueException) and (m := _RCLPY_RANGE_ERROR.search(text)):
        return InputError(
            f"parameter '{name_of}{m['name']}'", f"must be in [{m['low']}, {m['high']}], got {m['value']}"
        )
    if not isinstance(exc, InputError) or node is None:
        return exc
    m = re.fullmatch(rf"parameter '(?:{re.escape(node_label(node))}\.)?(?P<name>[^']+)'", exc.where)
    if m is None:
        return exc
    # the node's name in front (in active_mapping three nodes share parameter names), the params file behind
    where = f"parameter '{node_label(node)}.{m['name']}'" if node.has_parameter(m["name"]) else exc.where
    note = _set_in(node, m["name"])
    problem = exc.problem if note in exc.problem else exc.problem + _notes(note)
    return exc if (where, problem) == (exc.where, exc.problem) else InputError(where, problem)


_RCLPY_TYPE_ERROR = re.compile(
    r"Trying to set parameter '(?P<name>[^']+)' to '(?P<value>.*)' of type '(?P<given>\w+)', "
    r"expecting type '(?:Type\.)?(?P<want>\w+)'",
    re.DOTALL,
)
"""rclpy's InvalidParameterTypeException message."""

_RCLPY_RANGE_ERROR = re.compile(
    r"Parameter (?P<name>\S+) out of range\.? Min: (?P<low>[^,]+), Max: (?P<high>[^,]+), value: (?P<value>[^:]+)"
)
"""rclpy's InvalidParameterValueException message for a value outside its descriptor's range."""


def misspelt_sections(node: Node, others: Iterable[str] = ()) -> list[tuple[str, str]]:
    """``(params file, section)`` for each section of ``node``'s params files whose name is close to the node's own
    but is not it, nor a wildcard, a roigsf node's or one of ``others`` (the process's other nodes): rcl applies a
    section only to the node it names, so a misspelt ``mappr:`` leaves every parameter in it unapplied.
    """
    name = node.get_name()
    skip = {name, *ROIGSF_NODE_NAMES, *others}
    return [
        (path, label)
        for path, label, pattern in _file_sections(node)
        if "*" not in (leaf := pattern.rsplit("/", 1)[-1])
        and leaf not in skip
        and difflib.get_close_matches(name, [leaf], n=1, cutoff=0.75)
    ]


def _file_sections(node: Node) -> Iterator[tuple[str, str, str]]:
    """``(params file, section label, node pattern)`` for every section of ``node``'s params files, in order."""
    for kind, path in ros_parameter_rules(node.context):
        if kind == "file":
            for label, pattern, _ in params_file_sections(path):
                yield path, label, pattern


def sections_elsewhere(node: Node, others: Iterable[str] = ()) -> list[tuple[str, str]]:
    """``(params file, section)`` for each section named for ``node`` without a namespace (its name, or its class's
    default name when it was renamed) that does not apply to it: ``mapper:`` is ``/mapper``, so under ``-r
    __ns:=/robot1`` (or as ``mapper_b``) none of its parameters reach the node, without a word from rcl. ``others``:
    the process's other nodes' fully qualified names (a section that applies to one of them is theirs).
    """
    fqn = node.get_fully_qualified_name()
    names = {node.get_name(), getattr(type(node), "default_name", "") or node.get_name()}
    return [
        (path, label)
        for path, label, pattern in _file_sections(node)
        if pattern.count("/") == 1  # `mapper:`; a section that names a namespace was meant for it
        and pattern[1:] in names
        and not _applies(pattern, fqn)
        and not any(_applies(pattern, o) for o in others)
    ]


def undeclared_overrides(node: Node, also_declared: Iterable[str] = ()) -> list[str]:
    """The overrides addressed to ``node`` (params files, ``-p``, its constructor) that it does not declare, sorted.

    rclpy ignores them without a word (its ``_parameter_overrides`` keeps them all); a misspelt name in a
    params file or ``-p`` would leave the node on its default. ``also_declared``: names another node of the
    process declares (a ``-p`` or ``/**:`` entry reaches every node); rclpy's own parameters are skipped.
    """
    known = set(also_declared)
    return sorted(
        name
        for name in getattr(node, "_parameter_overrides", {})
        if not node.has_parameter(name)
        and name not in known
        and name not in RCLPY_PARAMETERS
        and not name.startswith(RCLPY_PARAMETER_PREFIXES)
    )


def check_parameter_overrides(
    node: Node,
    explicit: Iterable[Parameter] | None = None,
    *,
    warn: bool = True,
    siblings: Sequence[Node] = (),
) -> list[str]:
    """Call once ``node`` declared all its parameters: an InputError for a value a later params file gave another type
    (:func:`overlay_type_conflicts`) or an undeclared one in ``explicit``, else ONE warning naming the other undeclared
    overrides (with the closest declared names) and one per misspelt section of its params files
    (:func:`misspelt_sections`) or section that misses its namespace or new name (:func:`sections_elsewhere`);
    returns the undeclared names.

    ``explicit``: the ``parameter_overrides`` given to the node's constructor, a call naming this node, so an
    unknown name there is an error; a params file or ``-p`` may carry other nodes' parameters (ROS ignores
    those), so they only warn. ``siblings``: the other nodes of the process, whose names are not typos here; a
    node on its own skips the names any node of the package declares (:func:`package_parameter_names`).
    """
    conflicts = overlay_type_conflicts(node)
    if conflicts:
        raise conflicts[0]
    declared = _declared_names(node)
    unknown_explicit = sorted({p.name for p in explicit or ()} - set(node.list_parameters([], 0).names))
    if len(unknown_explicit) == 1:
        name = unknown_explicit[0]
        raise InputError(f"parameter '{node_label(node)}.{name}'", f"not declared by this node{_hint(name, declared)}")
    if unknown_explicit:
        where = "parameters " + ", ".join(f"'{node_label(node)}.{name}'" for name in unknown_explicit)
        hints = "; ".join(f"{name}: {', '.join(c)}" for name in unknown_explicit if (c := _closest(name, declared)))
        raise InputError(where, "not declared by this node" + (f" (closest declared {hints})" if hints else ""))
    others = [n for n in siblings if n is not node]
    also = [name for other in others for name in _declared_names(other)]
    ignored = undeclared_overrides(node, also if others else package_parameter_names())
    if warn and ignored:
        by = " nor by " + ", ".join(n.get_name() for n in others) if others else " nor by any other roigsf node"
        names = ", ".join(f"{name}{_hint(name, declared + also)}{_notes(_set_in(node, name))}" for name in ignored)
        node.get_logger().warning(f"ignored parameter(s) not declared by this node{by}: {names}")
    if warn:
        for path, section in misspelt_sections(node, [n.get_name() for n in others]):
            node.get_logger().warning(
                f"section '{section}' in {path} looks like a misspelling of '{node.get_name()}': "
                "its parameters are not applied"
            )
        fqn = node.get_fully_qualified_name()
        for path, section in sections_elsewhere(node, [n.get_fully_qualified_name() for n in others]):
            node.get_logger().warning(
                f"section '{section}' in {path} does not apply to this node, which runs as '{fqn}': its parameters "
                f"are not applied (name the section '{fqn}', or '/**/{node.get_name()}' for any namespace)"
            )
    return ignored


class SystemNode(Node):
    """A node of the active-mapping system; ``shared``: the in-process map (None: the node runs on its own).

    Subclasses set :attr:`default_name` and build everything in :meth:`_setup`. A set-up that raises
    destroys the half-built node (rclpy's part only: a subclass's ``destroy_node`` expects a whole node); a bad
    parameter's error names its params file (:func:`parameter_error`).
    Then :func:`check_parameter_overrides` runs: an unknown name in ``parameter_overrides`` raises (the
    whole node destroyed), one in a params file or ``-p`` is logged, unless ``warn_undeclared`` is false (a
    process of several nodes checks them together, see ``active_mapping.build_nodes``).
    """

    default_name = ""

    def __init__(
        self,
        *,
        context: Context | None = None,
        parameter_overrides: list[Parameter] | None = None,
        shared: SharedMapper | None = None,
        node_name: str | None = None,
        warn_undeclared: bool = True,
    ) -> None:
        super().__init__(node_name or self.default_name, context=context, parameter_overrides=parameter_overrides)
        try:
            self._setup(shared)
        except BaseException as exc:
            error = parameter_error(self, exc)  # the params file named, while the node can still say its name
            Node.destroy_node(self)
            if error is exc:
                raise
            raise error from None
        try:  # the overrides addressed to this node that it does not declare (logged unless warn_undeclared is off)
            self.ignored_parameters = check_parameter_overrides(self, parameter_overrides, warn=warn_undeclared)
        except BaseException:
            self.destroy_node()
            raise
        self.add_on_set_parameters_callback(_refuse_sim_time_change)
        if self.get_parameter("use_sim_time").value:  # said once if no /clock comes: every timer of the node waits
            steady = Clock(clock_type=ClockType.STEADY_TIME)
            self._sim_clock_check = self.create_timer(SIM_CLOCK_GRACE_S, self._check_sim_clock, clock=steady)

    def _check_sim_clock(self) -> None:
        """With ``use_sim_time`` on and the clock still at 0, say why the node's status and timers are silent."""
        self.destroy_timer(self._sim_clock_check)
        if self.get_clock().now().nanoseconds == 0:
            self.get_logger().warning(
                f"use_sim_time is true but no time came on /clock within {SIM_CLOCK_GRACE_S:g} s: this node's timers "
                "(~/status among them) wait for it; play the bag with a player that publishes /clock (`ros2 bag play "
                "--clock`; this package's bag_player does not), or leave use_sim_time off"
            )

    def _setup(self, shared: SharedMapper | None) -> None:
        raise NotImplementedError


SIM_CLOCK_GRACE_S = 5.0
"""How long a node with ``use_sim_time`` waits for a time on /clock before it says its timers are stopped."""


def _refuse_sim_time_change(params: list[Parameter]) -> SetParametersResult:
    """Refuse ``use_sim_time`` changed on a running node, as every other parameter of the package's nodes (read-only):
    switched on with nothing on /clock, every timer stopped (~/status too) and every wall-time request read as from
    the future, without a word.
    """
    if any(p.name == "use_sim_time" for p in params):
        return SetParametersResult(successful=False, reason=f"use_sim_time is {READ_AT_START}")
    return SetParametersResult(successful=True)


def changed_parameters(node: Node, exclude: Iterable[str] = ()) -> dict[str, Any]:
    """The parameters ``node`` declared (:func:`declare`) whose values differ from their defaults, topic and service
    names left out (a start-up line names those in full), and ``exclude``: for a start-up line, which named only the
    method's settings (``max_candidates=16`` or ``input_width=80`` went unsaid).
    """
    skip = set(exclude)
    out = {}
    for name, default in getattr(node, "_roigsf_defaults", {}).items():
        if name in skip or name.endswith(("_topic", "_service")):
            continue
        value = node.get_parameter(name).value
        if not _same_value(list(value) if isinstance(value, tuple) else value, default):
            out[name] = value
    return out


def settings_text(changed: dict[str, Any]) -> str:
    """``"; a=1, b=x"`` for a start-up line, from the settings off their defaults (``Config.changed``); "" for none:
    a node's log then says which settings beyond the defaults (a params file, an overlay) it runs with.
    """
    return "; " + ", ".join(f"{k}={v}" for k, v in changed.items()) if changed else ""


def check_positive(name: str, value: float, allow_zero: bool = False) -> float:
    """``value`` if it is > 0 (or >= 0), else an InputError naming parameter ``name``."""
    ok = value >= 0 if allow_zero else value > 0
    if not ok or value != value:
        raise InputError(f"parameter '{name}'", f"must be {'>= 0' if allow_zero else '> 0'}, got {value}")
    return value


def check_frame_id(name: str, value: str) -> str:
    """A frame parameter's value if it names a frame; an empty one is refused at start-up (it was taken, and every
    request in the map frame was then refused as "not the map frame ''", every output stamped in no frame), and so is
    one with a leading '/' (ROS 1's habit: every output header carried it, and tf2 refuses it).
    """
    if not value.strip():
        raise InputError(f"parameter '{name}'", "must name a TF frame (e.g. map), got an empty string")
    if value.startswith("/"):  # kept as given, it went into every header, and tf2 refuses such a frame id
        raise InputError(f"parameter '{name}'", f"TF frame ids do not start with '/' (tf2 refuses them): write "
                         f"{value.lstrip('/')!r}, not {value!r}")  # fmt: skip
    return value


def check_input_size(width: int, height: int) -> tuple[int | None, int | None] | None:
    """The ``input_width`` / ``input_height`` parameters as a size (0 = the camera's side; None: both 0), each side
    checked now (>= 0, at most :data:`MAX_IMAGE_SIDE`), not as a drop of every frame once the camera publishes.
    """
    for name, value in (("input_width", width), ("input_height", height)):
        check_positive(name, value, allow_zero=True)
        if value > MAX_IMAGE_SIDE:
            raise InputError(f"parameter '{name}'", f"must be at most {MAX_IMAGE_SIDE} px, got {value}")
    return None if not width and not height else (width or None, height or None)


__all__ = [
    "BAD_PARAMETER_ERRORS",
    "RCLPY_PARAMETERS",
    "RCLPY_PARAMETER_PREFIXES",
    "SystemNode",
    "changed_parameters",
    "check_frame_id",
    "check_input_size",
    "check_parameter_overrides",
    "check_positive",
    "check_ros_name",
    "declare",
    "declare_config",
    "field_docs",
    "misspelt_sections",
    "node_label",
    "package_config_folder",
    "parameter_error",
    "parameter_source",
    "params_file_sections",
    "remember_ros_args",
    "ros_parameter_rules",
    "settings_text",
    "undeclared_overrides",
]
