"""``roigsf ros``: talk to running roigsf nodes without the ros2 CLI, which ROS 2 from PyPI lacks.

``roigsf ros status mapper`` prints the next ``~/status`` of a node (its JSON counters); ``roigsf ros nbv --candidates
poses.txt`` asks the planner's ``~/get_next_best_view`` which of the poses (a traj.txt: one camera-to-world 4x4 a line,
OpenCV axes, in the map frame) to take and prints the ranking; ``save-map``, ``load-map`` and ``publish-mesh`` call the
mapper's services, ``finish`` the selector's. Each runs a hidden node (not counted by the nodes' start-up waits) in its
own context on ``ROS_DOMAIN_ID`` (or ``--domain-id``), with ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` unless the
environment sets another range. Exit 0 when the node answered yes, 1 when it answered no (its message on stderr), 2
when it could not be reached in ``--wait`` seconds (the error names the service or topic, the domain and the discovery
range), did not answer in ``--timeout``, or the input was bad (a pose file, the domain, a folder of no name of its own).
"""

from __future__ import annotations

import argparse
import contextlib
import difflib
import json
import os
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from roigsf_ros.cli import OVERWRITE_HELP
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.ros_domain import check_domain_id, domain_id_from_env

DEFAULT_WAIT_S = 10.0
"""Seconds to find the node's service or status topic."""
DEFAULT_TIMEOUT_S = 120.0
"""Seconds a service may take to answer (a planner's first request on a cold machine compiles kernels)."""
DEFAULT_STATUS_TIMEOUT_S = 5.0
"""Seconds to wait for a ``~/status`` message once the topic is found (the nodes publish it once a second)."""


def node_path(node: str) -> str:
    """The fully qualified name of a node given as ``mapper``, ``/mapper`` or ``/robot1/mapper``."""
    name = node.strip()
    if not name.strip("/") or any(c.isspace() for c in name):
        raise InputError("NODE", f"not a node name: {node!r} (e.g. mapper, /robot1/mapper)")
    return "/" + name.strip("/")


def domain_id_of(domain_id: int | None) -> int | None:
    """``--domain-id``, else ``ROS_DOMAIN_ID`` (None: unset, rcl's 0), each checked naming where it came from."""
    return check_domain_id(domain_id) if domain_id is not None else domain_id_from_env()


def directory_arg(text: str) -> str:
    """The absolute folder ``save-map`` / ``load-map`` send (the node's working folder may be another); ``~`` is
    the home folder; an empty name, ``.``, ``..`` or ``/`` are refused here, as the mapper refuses them (given as
    an absolute path they would slip past its check and name the caller's folder).
    """
    expanded = os.path.expanduser(text.strip())
    name = os.path.basename(os.path.normpath(expanded)) if expanded else ""
    if name in ("", ".", "..") or os.path.normpath(expanded) == os.sep:
        raise InputError("DIR", f"{text!r} names no folder of its own: give the map's folder, e.g. /tmp/map")
    return os.path.abspath(expanded)


def _where(domain_id: int | None) -> str:
    """The domain and discovery range this command looks in, for an error that could not reach a node."""
    domain = domain_id_of(domain_id)
    domain = 0 if domain is None else domain
    return f"ROS_DOMAIN_ID={domain}, ROS_AUTOMATIC_DISCOVERY_RANGE={os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE')}"


def nodes_seen(ros: Any, wanted: str) -> str:
    """`` nodes seen: /a, /b (did you mean /b?)`` (or `` no node seen``): what the graph holds, for an error about a
    node that did not answer (a mistyped name waited its whole ``--wait`` with no word of what was there).
    """
    names = sorted({f"{ns.rstrip('/')}/{n}" for n, ns in ros.get_node_names_and_namespaces() if not n.startswith("_")})
    if not names:
        return " no node seen"
    close = difflib.get_close_matches(wanted, names, n=1, cutoff=0.6)
    shown = ", ".join(names[:12]) + (f" and {len(names) - 12} more" if len(names) > 12 else "")
    return f" nodes seen: {shown}" + (f" (did you mean {close[0]}?)" if close and close[0] != wanted else "")


@contextlib.contextmanager
def ros_node(domain_id: int | None) -> Iterator[tuple[Any, Any]]:
    """A hidden node and a single-threaded executor in a fresh context; all shut down on the way out."""
    domain_id = domain_id_of(domain_id)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    context = rclpy.Context()
    rclpy.init(args=["roigsf"], context=context, domain_id=domain_id, signal_handler_options=SignalHandlerOptions.NO)
    node = None
    executor = None
    try:
        node = rclpy.create_node(f"_roigsf_ros_{os.getpid()}", context=context)  # '_': hidden
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        yield node, executor
    finally:
        if executor is not None:
            executor.shutdown()
        if node is not None:
            node.destroy_node()
        context.try_shutdown()


def call_service(srv_type: Any, service: str, request: Any, args: argparse.Namespace) -> Any:
    """The response of ``service`` to ``request``; InputError naming the service when it is absent or silent."""
    with ros_node(args.domain_id) as (node, executor):
        client = node.create_client(srv_type, service)
        if not client.wait_for_service(timeout_sec=args.wait):
            where, seen = _where(args.domain_id), nodes_seen(node, service.rsplit("/", 1)[0])
            raise InputError(service, f"no such service within {args.wait:g} s: is the node running ({where})?{seen}")
        future = client.call_async(request)
        executor.spin_until_future_complete(future, timeout_sec=args.timeout)
        if not future.done():
            client.remove_pending_request(future)
            raise InputError(service, f"no answer within {args.timeout:g} s (--timeout)")
        return future.result()


def read_status(node: str, args: argparse.Namespace) -> dict[str, Any]:
    """The next ``~/status`` message of ``node``, parsed; InputError naming the topic when none comes."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String

    topic = node_path(node) + "/status"
    got: list[str] = []
    qos = QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=1,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )
    with ros_node(args.domain_id) as (ros, executor):
        ros.create_subscription(String, topic, lambda msg: got.append(msg.data), qos)
        _spin_until(executor, lambda: ros.count_publishers(topic) > 0, args.wait)
        if ros.count_publishers(topic) == 0:
            where, seen = _where(args.domain_id), nodes_seen(ros, node_path(node))
            why = f"no publisher within {args.wait:g} s: is {node_path(node)} running ({where})?{seen}"
            raise InputError(topic, why)
        _spin_until(executor, lambda: bool(got), args.timeout)
        if not got:
            raise InputError(topic, f"nothing published within {args.timeout:g} s (is its status_rate_hz 0?)")
    try:
        status = json.loads(got[0])
    except json.JSONDecodeError as exc:
        raise InputError(topic, f"not JSON: {exc}") from None
    if not isinstance(status, dict):
        raise InputError(topic, f"not a JSON object: {got[0][:80]!r}")
    return status


def _spin_until(executor: Any, done: Callable[[], bool], timeout_s: float) -> None:
    """Spin ``executor`` in 0.1 s steps until ``done()`` or ``timeout_s`` has passed."""
    import time

    end = time.monotonic() + timeout_s
    while not done() and time.monotonic() < end:
        executor.spin_once(timeout_sec=min(0.1, max(end - time.monotonic(), 0.0)))


def candidates_request(path: Path, frame_id: str, top_k: int, mode: str) -> Any:
    """A ``GetNextBestView`` request of the poses in ``path`` (traj.txt: camera-to-world 4x4 a line, OpenCV axes)."""
    from geometry_msgs.msg import Pose, PoseArray

    from roigsf_interfaces.srv import GetNextBestView
    from roigsf_ros.core.camera import matrix_to_quat_xyzw
    from roigsf_ros.data.replica import load_traj

    if top_k < 0:
        raise InputError("--top-k", f"must be >= 0 (0: all, ranked), got {top_k}")
    poses = load_traj(path)
    if len(poses) == 0:
        raise InputError(path, "holds no pose")
    req = GetNextBestView.Request(top_k=top_k, mode=mode)
    req.candidates = PoseArray()
    req.candidates.header.frame_id = frame_id  # unstamped: never "stale"
    for T in poses:  # as nodes.map_msgs.matrix_to_pose does; that module loads torch, 5 s of a 2 s command
        pose = Pose()
        pose.position.x, pose.position.y, pose.position.z = (float(v) for v in T[:3, 3])
        q = matrix_to_quat_xyzw(T[:3, :3])
        pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = (float(v) for v in q)
        req.candidates.poses.append(pose)
    return req


def nbv_answer(res: Any) -> dict[str, Any]:
    """The planner's response as JSON-ready data."""
    p, q = res.best_pose.pose.position, res.best_pose.pose.orientation
    return {
        "success": bool(res.success),
        "message": res.message,
        "best_index": int(res.best_index),
        "best_pose": {
            "frame_id": res.best_pose.header.frame_id,
            "position_m": [p.x, p.y, p.z],
            "quaternion_xyzw": [q.x, q.y, q.z, q.w],
        },
        "top_k_indices": [int(i) for i in res.top_k_indices],
        "fused_scores": [float(v) for v in res.fused_scores],
        "fisher_scores": [float(v) for v in res.fisher_scores],
        "close_front_scores": [float(v) for v in res.close_front_scores],
    }


def nbv_table(answer: dict[str, Any]) -> str:
    """The ranking as a readable table: rank, candidate (line of the file, from 1), fused, Eq. 10 and Eq. 14 scores."""
    lines = [f"{'rank':>4}  {'line':>5}  {'fused':>9}  {'fisher (Eq. 10)':>15}  {'close-front (Eq. 14)':>20}"]
    for rank, i in enumerate(answer["top_k_indices"], 1):
        fused, fisher, close = (answer[k][i] for k in ("fused_scores", "fisher_scores", "close_front_scores"))
        lines.append(f"{rank:>4}  {i + 1:>5}  {fused:>9.4g}  {fisher:>15.4g}  {close:>20.4g}")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------ handlers
def _status(args: argparse.Namespace) -> int:
    status = read_status(args.node, args)
    print(json.dumps(status, indent=None if args.compact else 2, sort_keys=True))
    return 0


def _nbv(args: argparse.Namespace) -> int:
    from roigsf_interfaces.srv import GetNextBestView
    from roigsf_ros.core.fileio import check_writable, write_json

    if args.out is not None:
        check_writable(Path(args.out))
    req = candidates_request(Path(args.candidates), args.frame_id, args.top_k, args.mode)
    service = node_path(args.node) + "/get_next_best_view"
    answer = nbv_answer(call_service(GetNextBestView, service, req, args))
    answer = {
        "service": service,
        "candidates": str(args.candidates),
        "n_candidates": len(req.candidates.poses),
        "mode": args.mode,
        **answer,
    }
    if args.out is not None:
        write_json(args.out, answer)
    if not answer["success"]:
        print(f"roigsf ros nbv: {service} answered no: {answer['message']}", file=sys.stderr)
        return 1
    pose = answer["best_pose"]
    print(f"{service}: best of {answer['n_candidates']}: line {answer['best_index'] + 1} of {args.candidates}")
    print(
        "  position (m) " + " ".join(f"{v:.4f}" for v in pose["position_m"]) + f" in '{pose['frame_id']}', "
        "quaternion (x y z w) " + " ".join(f"{v:.4f}" for v in pose["quaternion_xyzw"])
    )
    if answer["message"]:
        print(f"  {answer['message']}")
    print(nbv_table(answer))
    return 0


def _answered(command: str, service: str, res: Any, hint: str = "") -> int:
    """0 and the node's message when it answered yes; 1 and its message (and ``hint``) on stderr when no."""
    if not res.success:
        print(f"roigsf ros {command}: {service} answered no: {res.message}{hint}", file=sys.stderr)
        return 1
    print(f"{service}: {res.message or 'done'}")
    return 0


def _save_map(args: argparse.Namespace) -> int:
    from roigsf_interfaces.srv import SaveMap

    service = node_path(args.node) + "/save_map"
    directory = directory_arg(args.directory)
    req = SaveMap.Request(directory=directory, with_mesh=args.with_mesh, overwrite=args.overwrite)
    res = call_service(SaveMap, service, req, args)
    hint = "; roigsf ros: pass --overwrite" if Path(directory).exists() and not args.overwrite else ""
    return _answered("save-map", service, res, hint)


def _load_map(args: argparse.Namespace) -> int:
    from roigsf_interfaces.srv import LoadMap

    service = node_path(args.node) + "/load_map"
    directory = directory_arg(args.directory)
    res = call_service(LoadMap, service, LoadMap.Request(directory=directory), args)
    return _answered("load-map", service, res)


def _trigger(command: str, name: str) -> Callable[[argparse.Namespace], int]:
    """A handler calling the ``std_srvs/Trigger`` service ``NODE/name``."""

    def handler(args: argparse.Namespace) -> int:
        from std_srvs.srv import Trigger

        service = node_path(args.node) + "/" + name
        res = call_service(Trigger, service, Trigger.Request(), args)
        return _answered(command, service, res)

    return handler


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``ros`` subcommand group."""
    p = sub.add_parser(
        "ros",
        help="talk to running nodes without the ros2 CLI: status, next best view, save/load map",
        description=__doc__,
    )
    group = p.add_subparsers(dest="ros_command", metavar="ACTION", required=True)

    def action(name: str, help_text: str, func: Callable[[argparse.Namespace], int], answer_s: float,
               node: str | None = None) -> Any:  # fmt: skip
        """A subcommand with the options every action has, and ``--NODE`` naming the node it calls (default NODE)."""
        a = group.add_parser(name, help=help_text, description=help_text)
        a.set_defaults(func=func)
        a.add_argument("--domain-id", type=int, metavar="N", help="ROS domain (default: ROS_DOMAIN_ID, else 0)")
        a.add_argument("--wait", type=_seconds("--wait"), default=DEFAULT_WAIT_S, metavar="S",
                       help=f"seconds to find the node (default {DEFAULT_WAIT_S:g})")  # fmt: skip
        a.add_argument("--timeout", type=_seconds("--timeout"), default=answer_s, metavar="S",
                       help=f"seconds for its answer (default {answer_s:g})")  # fmt: skip
        if node is not None:
            option = {"nbv_planner": "--planner", "mapper": "--mapper", "keyframe_selector": "--selector"}[node]
            a.add_argument(option, dest="node", default=node, metavar="NODE", help=f"the node (default {node})")
        return a

    a = action("status", "print a node's next ~/status (JSON counters)", _status, DEFAULT_STATUS_TIMEOUT_S)
    a.add_argument("node", metavar="NODE", help="mapper, nbv_planner, keyframe_selector, or /NS/NAME")
    a.add_argument("--compact", action="store_true", help="one line of JSON instead of indented")

    a = action("nbv", "ask the planner which of the candidate poses to take next", _nbv, DEFAULT_TIMEOUT_S,
               "nbv_planner")  # fmt: skip
    a.add_argument(
        "--candidates",
        required=True,
        metavar="TRAJ",
        help="candidate poses: a traj.txt (a camera-to-world 4x4, row-major, a line; OpenCV axes), at most the "
        "planner's max_candidates (64 by default)",
    )
    a.add_argument("--frame-id", default="", metavar="FRAME",
                   help="the poses' frame (default empty: the planner's map frame)")  # fmt: skip
    a.add_argument("--top-k", type=int, default=0, metavar="K", help="rank the K best (default 0: all)")
    a.add_argument("--mode", default="", help="score mode (default empty: the planner's `mode` parameter)")
    a.add_argument(
        "--out",
        metavar="FILE.json",
        help="also write the answer as JSON (its indices count candidates from 0; the table's lines from 1)",
    )

    a = action("save-map", "ask the mapper to save its map (map.ply, keyframes.json)", _save_map, DEFAULT_TIMEOUT_S,
               "mapper")  # fmt: skip
    a.add_argument("directory", metavar="DIR", help="the folder to write (made whole or not at all)")
    a.add_argument("--with-mesh", action="store_true", help="also the TSDF mesh (mesh.ply; slower)")
    a.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP.format(what="saved map", out="DIR"))

    a = action("load-map", "ask the mapper to replace its map with a saved one", _load_map, DEFAULT_TIMEOUT_S, "mapper")
    a.add_argument("directory", metavar="DIR", help="a folder written by save-map or `roigsf map`")
    action("publish-mesh", "ask the mapper to publish its mesh on ~/mesh", _trigger("publish-mesh", "publish_mesh"),
           DEFAULT_TIMEOUT_S, "mapper")  # fmt: skip
    action("finish", "tell the keyframe selector the stream has ended", _trigger("finish", "finish"),
           DEFAULT_TIMEOUT_S, "keyframe_selector")  # fmt: skip


def _seconds(option: str) -> Callable[[str], float]:
    """An argparse type: a finite number of seconds > 0, refused naming ``option``."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{option}: not a number of seconds: {text!r}") from None
        if not 0 < value < 1e6:
            raise argparse.ArgumentTypeError(f"{option}: must be in (0, 1e6) seconds, got {text}")
        return value

    return parse


__all__ = [
    "call_service",
    "candidates_request",
    "nbv_answer",
    "nbv_table",
    "node_path",
    "read_status",
    "register",
    "ros_node",
]
