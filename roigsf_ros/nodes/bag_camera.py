"""Which camera settings the camera nodes (mapper, keyframe selector) will read a bag with, resolved before they start.

``roigsf demo`` runs the nodes on a bag and evaluates the map against the same frames: it needs the settings the nodes
will end up with (their params files, ``--realsense``'s RealSense names, ``--set`` values, in that order), with ``auto``
transports named from the bag, and it must refuse settings with which a node would read no frame of the bag before
anything starts. A short-lived node of each camera node's name declares the camera parameters, so rcl resolves them
exactly as for the node itself.
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from roigsf_ros.core.errors import InputError
from roigsf_ros.data.bags import AUTO, BagReader, CameraTopics, bag_topic_types, realsense_topics
from roigsf_ros.nodes.node_params import context_with_params_files, parameter_error

if TYPE_CHECKING:
    from rclpy.context import Context


class NoFrameError(InputError):
    """The mapper's camera settings read no frame of the bag (a caller may add a hint about the bag's topics)."""


CAMERA_NODES = ("mapper", "keyframe_selector")
"""The nodes that read the camera topics (``roigsf_ros.nodes.mapper.camera_params``)."""
CAMERA_PARAMETERS = {
    "color": "color_topic",
    "depth": "depth_topic",
    "camera_info": "camera_info_topic",
    "pose": "pose_topic",
    **{name: name for name in ("pose_source", "tf_parent_frame", "tf_child_frame", "tf_topic", "tf_static_topic")},
    **{name: name for name in ("tf_tolerance_s", "color_transport", "depth_transport")},
}
"""CameraTopics field -> the camera nodes' parameter that sets it."""
_PROBED = {
    *CAMERA_PARAMETERS.values(),
    *("tf_wait_s", "tf_wait_frames", "tf_cache_s", "input_width", "input_height", "camera_reliability"),
    "pending_frames",
}
"""Every parameter ``camera_params`` declares: the ``--set`` values a probe node gets."""
REALSENSE_FIELDS = ("color", "depth", "camera_info", "pose_source", "tf_child_frame")
"""The CameraTopics fields :func:`~roigsf_ros.data.bags.realsense_topics` names (``--realsense`` sets them)."""


@dataclass(frozen=True)
class BagCamera:
    """How the camera nodes read a bag's camera, and the node parameters that make the nodes read it the same way."""

    topics: CameraTopics
    """The mapper's camera settings resolved against the bag: the frames the report is evaluated on."""
    params: dict[str, dict[str, Any]]
    """Node parameters: the ``--set`` ones over ``--realsense``'s, ``auto`` transports replaced by the bag's."""
    play: tuple[str, ...]
    """The bag's topics a camera node reads: what the player plays."""


def realsense_parameters(namespace: str) -> dict[str, Any]:
    """The camera parameters ``--realsense NS`` sets: RealSense names, pose from TF, transports from the bag."""
    t = realsense_topics(namespace, color_transport=AUTO, depth_transport=AUTO)
    fields = (*REALSENSE_FIELDS, "color_transport", "depth_transport")
    return {CAMERA_PARAMETERS[f]: getattr(t, f) for f in fields}


def _node_parameter(node: str, where: str) -> str:
    """An error's ``parameter 'NAME'`` as ``parameter 'NODE.NAME'`` (the demo runs two camera nodes)."""
    m = re.fullmatch(r"parameter '([^'.]+)'", where)
    return f"parameter '{node}.{m[1]}'" if m else where


def node_camera(context: Context, node: str, overrides: dict[str, Any]) -> CameraTopics:
    """The camera settings node ``node`` will run with: a short-lived node of that name declares its camera
    parameters under the context's params files and ``overrides`` (rcl resolves them exactly as for the node).
    """
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    from roigsf_ros.nodes.mapper import camera_params

    given = [Parameter(k, value=list(v) if isinstance(v, tuple) else v) for k, v in overrides.items() if k in _PROBED]
    probe = Node(node, context=context, parameter_overrides=given, start_parameter_services=False, enable_rosout=False)
    try:
        return camera_params(probe).topics
    except InputError as exc:
        named = parameter_error(probe, exc)  # "(set in FILE)" as the node itself says it
        named = named if isinstance(named, InputError) else exc
        raise InputError(_node_parameter(node, named.where), named.problem) from None
    finally:
        probe.destroy_node()


def first_frame(bag: Path, topics: CameraTopics, present: dict[str, str]) -> tuple[CameraTopics, InputError | None]:
    """``topics`` resolved against the bag's ``present`` topics, and None if they read a first frame of it, else the
    reader's error: a missing topic or one of another type, or no complete frame (incomplete stamps, no pose on TF).
    """
    try:
        resolved = topics.in_bag(present, bag)
        with BagReader(bag, resolved) as reader:
            if next(reader.frames(), None) is not None:
                return resolved, None
            why = f"{reader.skipped_frames} incomplete stamps"
            if reader.no_tf:
                why += f", {reader.no_tf} complete frame(s) without a pose on TF: {reader.last_tf_error}"
    except InputError as exc:
        return topics, exc
    return resolved, InputError(bag, f"no complete frame on {', '.join(resolved.types())} ({why})")


def bag_camera(
    bag: Path,
    params: dict[str, dict[str, Any]] | None = None,
    params_files: Sequence[Path] = (),
    realsense: str | None = None,
    domain_id: int | None = None,
) -> BagCamera:
    """The bag's camera as the nodes will read it: their camera parameters (params files, then ``realsense``'s, then
    ``params``, which win), ``auto`` transports resolved from the bag, checked to read a frame of it.

    :class:`NoFrameError` with the reader's error when the mapper reads no frame; InputError naming the parameters when
    the mapper's and the selector's settings differ so that one of them would read nothing.
    """
    node_params = {k: dict(v) for k, v in (params or {}).items()}
    if realsense is not None:
        rs = realsense_parameters(realsense)
        for node in CAMERA_NODES:
            node_params[node] = rs | node_params.get(node, {})
        node_params.setdefault("nbv_planner", {}).setdefault("camera_info_topic", rs["camera_info_topic"])
    present = bag_topic_types(bag)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    context = context_with_params_files(params_files, domain_id)
    try:
        wanted = {node: node_camera(context, node, node_params.get(node, {})) for node in CAMERA_NODES}
    finally:
        context.try_shutdown()
    read = {wanted["mapper"]: first_frame(bag, wanted["mapper"], present)}
    read.setdefault(wanted["keyframe_selector"], first_frame(bag, wanted["keyframe_selector"], present))
    (mapper, mapper_error), (selector, selector_error) = (read[wanted[n]] for n in CAMERA_NODES)
    if (mapper_error is None) != (selector_error is None):  # one reads the bag, the other nothing
        node, peer = ("mapper", "keyframe_selector") if mapper_error else ("keyframe_selector", "mapper")
        error = mapper_error or selector_error
        fields = [f for f in CAMERA_PARAMETERS if getattr(wanted[node], f) != getattr(wanted[peer], f)]
        peer_read = mapper if peer == "mapper" else selector

        def theirs(f: str) -> str:  # an auto transport with what it is in this bag
            value = getattr(wanted[peer], f)
            return f"auto, here {getattr(peer_read, f)}" if value == AUTO else str(value)

        mine = ", ".join(f"{CAMERA_PARAMETERS[f]}={getattr(wanted[node], f)}" for f in fields)
        theirs_all = ", ".join(theirs(f) for f in fields)
        names = ", ".join(f"'{node}.{CAMERA_PARAMETERS[f]}'" for f in fields)
        raise InputError(
            f"parameter{'s' if len(fields) > 1 else ''} {names}",
            f"{mine} (the {peer}'s: {theirs_all}): the {node} would read no frame of the bag: {error}",
        )
    if mapper_error is not None:
        raise NoFrameError(mapper_error.where, mapper_error.problem)
    for node, resolved in zip(CAMERA_NODES, (mapper, selector), strict=True):
        for stream in ("color", "depth"):
            if getattr(wanted[node], f"{stream}_transport") == AUTO:  # the nodes need it named
                node_params.setdefault(node, {})[f"{stream}_transport"] = getattr(resolved, f"{stream}_transport")
    topics = {t for r in (mapper, selector) for t in (*r.types(), *r.tf_types())}
    return BagCamera(mapper, node_params, tuple(sorted(topics & set(present))))
