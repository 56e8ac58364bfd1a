"""Parameter and spinning helpers shared by the roigsf nodes.

A method config dataclass (MapperConfig, NBVConfig) becomes one ROS parameter per field with the
same name and default (its attribute docstring as the description), so ``--ros-args -p`` and
``--params-file`` reach every tunable; :func:`init_ros` and :func:`run_nodes` are the console scripts'
start and spin loop.
"""

from __future__ import annotations

import argparse
import ast
import concurrent.futures
import contextlib
import dataclasses
import functools
import inspect
import itertools
import os
import signal
import sys
import textwrap
import threading
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any

import rclpy
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.executors import Executor, ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import remove_ros_args

from roigsf_ros.core.errors import InputError

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


def declare(node: Node, name: str, default: Any, description: str) -> Any:
    """Declare one parameter with a default and a description; returns its (possibly overridden) value."""
    value = list(default) if isinstance(default, tuple) else default
    try:
        return node.declare_parameter(name, value, ParameterDescriptor(description=description)).value
    except InvalidParameterTypeException as exc:  # e.g. `-p near_m:=0`: an int where the default is a float
        hint = " (write a float with a point, e.g. 0.0)" if isinstance(default, float) else ""
        kind = _KIND_WORDS.get(type(default), f"a {type(default).__name__}")
        raise InputError(
            f"parameter '{node.get_name()}.{name}'", f"must be {kind} like its default {default!r}{hint}; {exc}"
        ) from None


def declare_config(node: Node, cls: type, skip: Iterable[str] = ()) -> dict[str, Any]:
    """Declare every field of the dataclass ``cls`` as a parameter (default = the field's); returns name -> value.

    Arrays come back as tuples, as the dataclasses hold them.
    """
    docs = field_docs(cls)
    defaults = cls()
    out: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        if f.name in skip:
            continue
        value = declare(node, f.name, getattr(defaults, f.name), docs.get(f.name, f"{cls.__name__}.{f.name}"))
        out[f.name] = tuple(value) if isinstance(value, list | tuple) else value
    return out


class SystemNode(Node):
    """A node of the active-mapping system; ``shared``: the in-process map (None: the node runs on its own).

    Subclasses set :attr:`default_name` and build everything in :meth:`_setup`. A set-up that raises
    destroys the half-built node (rclpy's part only: a subclass's ``destroy_node`` expects a whole node).
    """

    default_name = ""

    def __init__(
        self,
        *,
        context: Context | None = None,
        parameter_overrides: list[Parameter] | None = None,
        shared: SharedMapper | None = None,
        node_name: str | None = None,
    ) -> None:
        super().__init__(node_name or self.default_name, context=context, parameter_overrides=parameter_overrides)
        try:
            self._setup(shared)
        except BaseException:
            Node.destroy_node(self)
            raise

    def _setup(self, shared: SharedMapper | None) -> None:
        raise NotImplementedError


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


GIL_SWITCH_INTERVAL_S = 0.0005
"""Python's thread switch interval in a node process (its default is 5 ms); ``ROIGSF_GIL_SWITCH_INTERVAL_S``
overrides it (0: keep Python's). A node runs Python threads beside each other: the executor's spin loop,
its callback pool and the mapper's worker, whose torch ops release the GIL and must take it back after
each op. While the spin loop runs Python, each take-back waits up to the interval (the "convoy effect"):
under the 4x replay an optimisation step took seconds, the worker inserted 0-1 keyframes in 55 s and the
executor took in a fifth of the frames (all of them, and 14 keyframes, at 0.5 ms)."""


def reduce_gil_switch_interval() -> float:
    """Lower ``sys.setswitchinterval`` to :data:`GIL_SWITCH_INTERVAL_S` (never raise it); returns the interval set."""
    raw = os.environ.get("ROIGSF_GIL_SWITCH_INTERVAL_S", "").strip()
    try:
        wanted = float(raw) if raw else GIL_SWITCH_INTERVAL_S
    except ValueError:
        raise InputError("ROIGSF_GIL_SWITCH_INTERVAL_S", f"not a number of seconds: {raw!r}") from None
    if wanted > 0:
        sys.setswitchinterval(min(wanted, sys.getswitchinterval()))
    return sys.getswitchinterval()


ROS_ARGS_HELP = """ROS arguments (after --ros-args):
  -p NAME:=VALUE         set a parameter (a float needs a decimal point: rate:=1.0)
  --params-file FILE     parameters from a YAML file (this package's config/<node>.yaml has every default)
  -r __node:=NAME        rename the node; -r OLD:=NEW remaps a topic"""


def script_args(program: str, description: str | None, args: list[str] | None, bag: bool = False) -> list[str]:
    """The console scripts' own command line: ``--help`` prints help and exits 0 before ROS starts.

    Plain (non-ROS) arguments are parsed by argparse, so anything unknown exits 2 with usage; with
    ``bag`` an optional positional BAG is accepted (as ``ros2 bag play BAG``) and becomes the ``bag``
    parameter. Returns the argument list for ``rclpy.init``.
    """
    argv = list(sys.argv if args is None else args)
    parser = argparse.ArgumentParser(
        prog=program,
        description=(description or "").strip(),
        epilog=ROS_ARGS_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    if bag:
        parser.add_argument("bag", nargs="?", metavar="BAG", help="bag folder or .mcap file (or -p bag:=PATH)")
    ns = parser.parse_args(remove_ros_args(argv)[1:])
    if bag and ns.bag:
        quoted = "'" + str(ns.bag).replace("'", "''") + "'"  # a YAML string, whatever the path looks like
        argv += ["--ros-args", "-p", f"bag:={quoted}"]
    return argv  # rclpy.init ignores the plain arguments


def init_ros(args: list[str] | None = None) -> None:
    """``rclpy.init`` for a console script: SIGINT/SIGTERM raise KeyboardInterrupt in the main thread.

    Also lowers the thread switch interval (:func:`reduce_gil_switch_interval`).

    rclpy's own handlers shut the context down inside the signal handler, under the executor's feet:
    callbacks still running then fail ("publisher's context is invalid", printed by rclpy as "exception
    was never retrieved") and a ``spin_once`` in progress raised RCLError (exit 1 with a traceback, 2 of 3
    Ctrl-Cs of a mapping ``active_mapping``). Here the script's ``finally`` stops the executor, destroys the
    nodes and shuts the context down last. A second signal during that clean-up exits at once (128 + signal).
    """
    reduce_gil_switch_interval()
    rclpy.init(args=sys.argv if args is None else args, signal_handler_options=SignalHandlerOptions.NO)
    signal.signal(signal.SIGINT, _interrupt)
    signal.signal(signal.SIGTERM, _interrupt)


def _interrupt(signum: int, frame: object) -> None:
    signal.signal(signal.SIGINT, _exit_now)
    signal.signal(signal.SIGTERM, _exit_now)
    raise KeyboardInterrupt


def _exit_now(signum: int, frame: object) -> None:
    print(f"interrupted again (signal {signum}): exiting without clean-up", file=sys.stderr)
    os._exit(128 + signum)


def shutdown_executor(executor: Executor) -> None:
    """Wait for the callbacks ``executor``'s threads still run, then shut it down; call once nothing spins it.

    The Jazzy wheel's ``Executor.shutdown`` does not wait (its ``_work_tracker.wait`` sits behind a test
    that is always false) and ``MultiThreadedExecutor`` leaves its thread pool running (ros2/rclpy#1309,
    newer than the wheel): a service callback still scoring then published through a destroyed node, and
    a queued handler triggered the destroyed guard condition (both printed "exception was never
    retrieved"). Nodes with long callbacks offer ``stop()`` to cut them short; call it first.
    """
    pool = getattr(executor, "_executor", None)
    if isinstance(pool, concurrent.futures.ThreadPoolExecutor):
        pool.shutdown(wait=True)
    executor.shutdown()


class BackgroundSpin:
    """Spin an executor in a thread (``spin_once`` until :meth:`stop`), then drain and shut it down.

    ``executor.shutdown()`` from another thread while ``spin()`` runs destroys the guard condition under
    handlers still queued (see :func:`shutdown_executor`); stopping the loop first avoids that.
    """

    def __init__(self, executor: Executor, name: str) -> None:
        self.executor = executor
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name=name, daemon=True)

    def _spin(self) -> None:
        context = self.executor.context
        with contextlib.suppress(ExternalShutdownException):
            while not self._stop.is_set() and context.ok():
                self.executor.spin_once(timeout_sec=0.1)

    def start(self) -> BackgroundSpin:
        """Start spinning; returns self."""
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 30.0) -> None:
        """Stop spinning, join the thread, wait for running callbacks, shut the executor down (idempotent)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                raise RuntimeError(f"{self._thread.name}: executor thread did not stop within {timeout_s:g} s")
        shutdown_executor(self.executor)


def run_nodes(
    program: str,
    build: Callable[[], list[Node]],
    args: list[str] | None = None,
    threads: int = 4,
    description: str | None = None,
) -> int:
    """Console-script body: init, build the nodes, spin them on a multi-threaded executor until Ctrl-C.

    Exit codes: 0 after Ctrl-C/shutdown, 2 when the parameters (or ``ROIGSF_GIL_SWITCH_INTERVAL_S``) are bad,
    the message naming them. Spins with ``spin_once`` in a loop (plain ``spin`` does not always return on
    SIGINT, see the notes).
    """
    args = script_args(program, description, args)
    try:
        init_ros(args)
    except InputError as exc:
        print(f"{program}: error: {exc}", file=sys.stderr)
        return 2
    nodes: list[Node] = []
    executor: MultiThreadedExecutor | None = None
    try:  # Ctrl-C may come at any point, also while the nodes or the executor are being built
        try:
            nodes = build()
        except BAD_PARAMETER_ERRORS as exc:
            float_hint = "expecting type 'DOUBLE'" in str(exc)
            hint = " (a float parameter needs a decimal point, e.g. 1.0)" if float_hint else ""
            print(f"{program}: error: {exc}{hint}", file=sys.stderr)
            return 2
        executor = MultiThreadedExecutor(num_threads=threads)
        for node in nodes:
            executor.add_node(node)
        while rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        for node in nodes:  # long service work gives up at once (see MapperNode.stop)
            stop = getattr(node, "stop", None)
            if callable(stop):
                stop()
        if executor is not None:
            shutdown_executor(executor)
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


__all__ = [
    "BAD_PARAMETER_ERRORS",
    "ROS_ARGS_HELP",
    "BackgroundSpin",
    "SystemNode",
    "check_positive",
    "declare",
    "declare_config",
    "field_docs",
    "init_ros",
    "reduce_gil_switch_interval",
    "run_nodes",
    "script_args",
    "settings_text",
    "shutdown_executor",
]
