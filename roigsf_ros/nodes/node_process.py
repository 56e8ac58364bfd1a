"""How a roigsf node process starts, spins and stops: the console scripts' command line, ``rclpy.init`` with clean
signal handling, the executor loop, and an executor spun in a thread (tests, the demo) that shuts down cleanly.
"""

from __future__ import annotations

import argparse
import ast
import concurrent.futures
import contextlib
import logging
import os
import re
import signal
import sys
import threading
from collections.abc import Callable
from pathlib import Path

import rclpy
import rclpy.logging
from rclpy.executors import Executor, ExternalShutdownException, MultiThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import get_default_context, remove_ros_args

from roigsf_ros.core.errors import InputError
from roigsf_ros.core.ros_domain import domain_id_from_env
from roigsf_ros.nodes.node_params import BAD_PARAMETER_ERRORS, parameter_error, remember_ros_args

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


_RCL_LOCATION = re.compile(r",? at [^,]*:\d+")
"""rcl's ``, at /project/src/parser.c:271`` source locations in its error messages."""

_RCL_RULE = re.compile(r"Couldn't parse (?P<what>[^:']+?): '(?P<arg>.*)'\.(?: Error: (?P<why>.*))?$", re.DOTALL)
"""rcl's message for an argument it could not parse: what kind, the argument, its reason."""


def ros_args_error(exc: Exception) -> InputError:
    """An InputError naming the ROS argument rclpy refused (``exc``: its RCLInvalidROSArgsError or
    UnknownROSArgsError), without rcl's source locations; a params file is checked here to say which of
    not found, unreadable or not valid YAML it is.
    """
    if isinstance(exc, _rclpy.UnknownROSArgsError):
        try:
            unknown = ", ".join(map(str, ast.literal_eval(str(exc))))  # rclpy's message is the list's repr
        except (ValueError, SyntaxError, TypeError):
            unknown = str(exc)
        return InputError("--ros-args", f"unknown ROS argument(s) {unknown} (see --help)")
    text = _RCL_LOCATION.sub("", str(exc)).removeprefix("Failed to parse ROS arguments: ").strip()
    rule = _RCL_RULE.match(text)
    if rule is None:
        return InputError("--ros-args", text)
    arg, why = rule["arg"], (rule["why"] or "").strip()
    flag, _, value = arg.partition(" ")
    if rule["what"] == "params file" and flag == "--params-file":
        path = Path(value)
        if not path.exists():
            return InputError(path, "params file not found")
        if not path.is_file() or not os.access(path, os.R_OK):
            return InputError(path, "params file cannot be read (not a readable file)")
        return InputError(path, f"not a valid YAML params file ({why})")
    if rule["what"] == "parameter override rule":
        if arg.endswith(":="):  # an empty value: rcl needs it quoted as YAML
            return InputError(f"'{arg}'", f"a parameter is set as -p NAME:=VALUE; an empty string is -p \"{value}''\"")
        return InputError(f"'{arg}'", "a parameter is set as -p NAME:=VALUE")
    if rule["what"] == "remap rule":
        return InputError(f"'{arg}'", "a remap is -r OLD:=NEW")
    return InputError(f"'{arg}'", f"cannot parse {rule['what']}" + (f" ({why})" if why else ""))


ROS_ARGS_ERRORS = (_rclpy.RCLInvalidROSArgsError, _rclpy.UnknownROSArgsError)
"""What rclpy raises for ROS arguments it cannot parse (reported by :func:`ros_args_error`, exit code 2)."""


def script_args(program: str, description: str | None, args: list[str] | None, bag: bool = False) -> list[str]:
    """The console scripts' own command line: ``--help`` prints help and exits 0 before ROS starts.

    Plain (non-ROS) arguments are parsed by argparse, so anything unknown exits 2 with usage; with
    ``bag`` an optional positional BAG is accepted (as ``ros2 bag play BAG``) and becomes the ``bag``
    parameter. ROS arguments rclpy cannot parse (a missing or invalid params file, ``-p NAME`` without
    ``:=VALUE``) exit 2 with one line naming them (:func:`ros_args_error`). Returns the argument list for
    ``rclpy.init``.
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
    try:
        plain = remove_ros_args(argv)
    except ROS_ARGS_ERRORS as exc:
        print(f"{program}: error: {ros_args_error(exc)}", file=sys.stderr)
        raise SystemExit(2) from None
    ns = parser.parse_args(plain[1:])
    if bag and ns.bag:
        quoted = "'" + str(ns.bag).replace("'", "''") + "'"  # a YAML string, whatever the path looks like
        argv += ["--ros-args", "-p", f"bag:={quoted}"]
    return argv  # rclpy.init ignores the plain arguments


class RosLogHandler(logging.Handler):
    """Python log records of the library (``roigsf_ros.*``: a frame without valid depth, a pose outside ``map``) through
    the ROS logger of their module's name, so a node process says them as its own lines are said: on the console with
    level and time, in its ROS log file and on ``/rosout`` (they came as bare lines on stderr).
    """

    def emit(self, record: logging.LogRecord) -> None:
        """Say ``record`` with the ROS logger of its name, at its level."""
        try:
            logger = rclpy.logging.get_logger(record.name)
            text = self.format(record)
            if record.levelno >= logging.ERROR:
                logger.error(text)
            elif record.levelno >= logging.WARNING:
                logger.warning(text)
            elif record.levelno >= logging.INFO:
                logger.info(text)
            else:
                logger.debug(text)
        except Exception:  # a log line must never take the node down
            self.handleError(record)


def route_library_logging() -> RosLogHandler:
    """Send the library's Python logging (``roigsf_ros``, warnings and up unless configured) through ROS logging
    (:class:`RosLogHandler`); once per process. Returns the handler.
    """
    library = logging.getLogger("roigsf_ros")
    for handler in library.handlers:
        if isinstance(handler, RosLogHandler):
            return handler
    handler = RosLogHandler()
    library.addHandler(handler)
    library.propagate = False  # said once, by ROS
    if library.level == logging.NOTSET:
        library.setLevel(logging.WARNING)  # what Python said without a handler
    return handler


def init_ros(args: list[str] | None = None) -> None:
    """``rclpy.init`` for a console script: SIGINT/SIGTERM raise KeyboardInterrupt in the main thread.

    Also lowers the thread switch interval (:func:`reduce_gil_switch_interval`) and sends the library's Python logging
    through ROS logging (:func:`route_library_logging`). ROS arguments rclpy cannot
    parse raise InputError (:func:`ros_args_error`), as a bad ``ROIGSF_GIL_SWITCH_INTERVAL_S`` or ``ROS_DOMAIN_ID``
    does. The arguments are noted (:func:`remember_ros_args`): the nodes' errors and warnings name their params files.

    rclpy's own handlers shut the context down inside the signal handler, under the executor's feet:
    callbacks still running then fail ("publisher's context is invalid", printed by rclpy as "exception
    was never retrieved") and a ``spin_once`` in progress raised RCLError (exit 1 with a traceback, 2 of 3
    Ctrl-Cs of a mapping ``active_mapping``). Here the script's ``finally`` stops the executor, destroys the
    nodes and shuts the context down last. A second signal during that clean-up exits at once (128 + signal).
    """
    reduce_gil_switch_interval()
    domain_id_from_env()  # a bad ROS_DOMAIN_ID: one line naming it, not rcl's traceback
    try:
        rclpy.init(args=sys.argv if args is None else args, signal_handler_options=SignalHandlerOptions.NO)
    except ROS_ARGS_ERRORS as exc:
        raise ros_args_error(exc) from None
    remember_ros_args(get_default_context(), sys.argv if args is None else args)
    route_library_logging()
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

    Exit codes: 0 after Ctrl-C/shutdown, 2 when the parameters, the ROS arguments (or
    ``ROIGSF_GIL_SWITCH_INTERVAL_S``) are bad, the message naming them. Spins with ``spin_once`` in a loop
    (plain ``spin`` does not always return on SIGINT, see the notes).
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
        except BAD_PARAMETER_ERRORS as exc:  # the nodes word their own; rclpy's are put in the same words
            print(f"{program}: error: {parameter_error(None, exc)}", file=sys.stderr)
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
    "GIL_SWITCH_INTERVAL_S",
    "ROS_ARGS_ERRORS",
    "ROS_ARGS_HELP",
    "BackgroundSpin",
    "RosLogHandler",
    "init_ros",
    "reduce_gil_switch_interval",
    "ros_args_error",
    "route_library_logging",
    "run_nodes",
    "script_args",
    "shutdown_executor",
]
