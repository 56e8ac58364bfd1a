"""``active_mapping``: the mapper, NBV planner and keyframe selector in one process, sharing one map.

The three nodes run on one multi-threaded executor and share a :class:`SharedMapper` object (no
serialisation: the planner and the selector read snapshots of the very map the mapper optimises).
Topics and services are the same as when the nodes run as separate processes, so tools and the bag
player see no difference. Parameters go to each node by its name, e.g. with a params file that has
``mapper:``, ``nbv_planner:`` and ``keyframe_selector:`` sections (config/*.yaml), or ``-p`` for a
name only one node declares::

    active_mapping --ros-args --params-file config/mapper.yaml -p policy:=gaus-slam
"""

from __future__ import annotations

import sys
from typing import Any

from rclpy.context import Context
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter

from roigsf_ros.nodes.keyframe_selector import KeyframeSelectorNode
from roigsf_ros.nodes.mapper import MapperNode
from roigsf_ros.nodes.nbv_planner import NBVPlannerNode
from roigsf_ros.nodes.node_params import check_parameter_overrides
from roigsf_ros.nodes.node_process import BackgroundSpin, reduce_gil_switch_interval, run_nodes, shutdown_executor
from roigsf_ros.nodes.shared_map import SharedMapper

NODE_NAMES = ("mapper", "nbv_planner", "keyframe_selector")


def _as_parameters(values: dict[str, Any] | None) -> list[Parameter] | None:
    """``{name: value}`` as rclpy Parameters (tuples become lists)."""
    if not values:
        return None
    return [Parameter(k, value=list(v) if isinstance(v, tuple) else v) for k, v in values.items()]


def build_nodes(
    context: Context | None = None, params: dict[str, dict[str, Any]] | None = None
) -> tuple[MapperNode, NBVPlannerNode, KeyframeSelectorNode]:
    """The mapper, planner and selector sharing one :class:`SharedMapper` (the ones built are destroyed on error).

    ``params``: ``{"mapper": {...}, "nbv_planner": {...}, "keyframe_selector": {...}}`` overrides
    (params files and ``--ros-args`` given to the context apply as well). An override that no node of the
    three declares is logged once per node it reached (a ``-p`` for one node reaches all three).
    """
    params = params or {}
    unknown = sorted(set(params) - set(NODE_NAMES))
    if unknown:
        raise ValueError(f"unknown node name(s) {', '.join(unknown)}; expected {', '.join(NODE_NAMES)}")
    shared = SharedMapper()
    built: list[Node] = []
    try:
        kw: dict[str, Any] = {"context": context, "shared": shared, "warn_undeclared": False}
        # The selector first, its camera deferred: a mistyped policy is refused before the planner's warm-up (1 s, a
        # minute with a cold cache) and the mapper's. The planner before the mapper: its warm-up came between the
        # mapper's camera subscriptions and the selector's, and a player waiting for one subscriber (its default)
        # started on the mapper's: the selector missed the first frames of the README's one-process command. The
        # selector subscribes right after the mapper.
        overrides = _as_parameters(params.get("keyframe_selector"))
        selector = KeyframeSelectorNode(parameter_overrides=overrides, defer_camera=True, **kw)
        built.append(selector)
        planner = NBVPlannerNode(parameter_overrides=_as_parameters(params.get("nbv_planner")), **kw)
        built.append(planner)
        mapper = MapperNode(parameter_overrides=_as_parameters(params.get("mapper")), **kw)
        built.append(mapper)
        selector.camera.subscribe()
        for node in built:
            node.ignored_parameters = check_parameter_overrides(node, siblings=built)
    except BaseException:
        for node in built:
            node.destroy_node()
        raise
    return mapper, planner, selector


class ActiveMapping:
    """The three nodes of one process (:func:`build_nodes`) with their shared map and executor.

    :meth:`start` spins the executor in a thread; :meth:`shutdown` stops it, joins every thread and
    destroys the nodes.
    """

    def __init__(
        self, context: Context | None = None, params: dict[str, dict[str, Any]] | None = None, threads: int = 4
    ) -> None:
        self.context = context
        self.mapper, self.planner, self.selector = build_nodes(context, params)
        self.shared = self.mapper.shared
        self.nodes: list[Node] = [self.mapper, self.planner, self.selector]
        self.executor = MultiThreadedExecutor(num_threads=threads, context=context)
        for node in self.nodes:
            self.executor.add_node(node)
        self._spin: BackgroundSpin | None = None

    def start(self) -> ActiveMapping:
        """Spin the executor in a background thread; returns self.

        Lowers the process's thread switch interval, as the console scripts do (see
        :func:`~roigsf_ros.nodes.node_process.reduce_gil_switch_interval`).
        """
        reduce_gil_switch_interval()
        self._spin = BackgroundSpin(self.executor, "active_mapping_executor").start()
        return self

    def status(self) -> dict[str, Any]:
        """The three nodes' status dicts."""
        return {
            "mapper": self.mapper.status(),
            "nbv_planner": self.planner.status(),
            "selector": self.selector.status(),
        }

    def shutdown(self) -> None:
        """Stop the executor, join its thread and the mapper's worker, destroy the nodes (idempotent)."""
        for node in self.nodes:  # long service work gives up at once (see MapperNode.stop)
            stop = getattr(node, "stop", None)
            if callable(stop):
                stop()
        if self._spin is not None:
            self._spin.stop()
        else:
            shutdown_executor(self.executor)
        for node in self.nodes:
            node.destroy_node()
        self.nodes = []

    def __enter__(self) -> ActiveMapping:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.shutdown()


def main(args: list[str] | None = None) -> int:
    """Console script ``active_mapping``: run the three nodes until Ctrl-C; exit 2 on a bad parameter."""
    return run_nodes("active_mapping", lambda: list(build_nodes()), args, description=__doc__)


if __name__ == "__main__":
    sys.exit(main())
