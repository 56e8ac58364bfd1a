"""Surfel maps and keyframe poses as ROS messages: ``sensor_msgs/PointCloud2``, ``PoseArray``, mesh ``Marker``, the
map's intrinsics as ``CameraInfo``.

The map cloud has one point per surfel with float32 fields (little-endian, packed, ``point_step`` =
4 x number of fields), all raw 2DGS parameters of :class:`roigsf_ros.render.surfels.SurfelMap`, so a round
trip is exact (the map is float32):

    x y z                       centre (metres, in ``frame_id``, default "map")
    qw qx qy qz                 rotation quaternion (w, x, y, z), as stored (normalised on use)
    log_scale_u log_scale_v     log of the tangent standard deviations (metres)
    opacity_logit               logit of the opacity
    sh_dc_0 sh_dc_1 sh_dc_2     zeroth SH coefficient per channel (colour = 0.5 + 0.2821 * sh_dc)
    sh_rest_0 .. sh_rest_8      only for degree-1 maps: [coefficient, channel] row-major
    rgb                         the surfel's colour packed as RViz reads it (uint32 0x00RRGGBB in a float32)
    htrain_<outputs>__<param>[_i]   optional: the mapper's running training Fisher (``Mapper.h_train``), one
                                field per component of each parameter it covers, e.g. ``htrain_color+depth__means_0``
                                (``<outputs>`` = its ``fisher_outputs`` joined by ``+``); read by :func:`cloud_h_train`

``rgb`` is derived (ignored when reading); the ``htrain_`` fields are optional; every other field is
required. Errors name the field.

The mesh marker of a large mesh is built as serialized CDR bytes (:func:`mesh_marker_cdr`, what a
publisher sends as is): one ``geometry_msgs/Point`` Python object per vertex costs seconds per 100k
triangles, the byte splice milliseconds.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from geometry_msgs.msg import Point, Pose, PoseArray, PoseStamped
from sensor_msgs.msg import CameraInfo, PointCloud2, PointField
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker

from roigsf_ros.core.camera import Intrinsics, matrix_to_quat_xyzw
from roigsf_ros.core.errors import InputError
from roigsf_ros.data.bags import camera_info_fields, pose_to_matrix
from roigsf_ros.render.surfels import SurfelMap

MAP_FRAME_ID = "map"
"""Default frame of the map cloud, keyframe poses and candidate poses."""

BASE_FIELDS = (
    "x", "y", "z", "qw", "qx", "qy", "qz", "log_scale_u", "log_scale_v", "opacity_logit",
    "sh_dc_0", "sh_dc_1", "sh_dc_2",
)  # fmt: skip
"""Required float32 fields of a map cloud, in the order they are written."""
SH_REST_FIELDS = tuple(f"sh_rest_{i}" for i in range(9))
"""Fields of the degree-1 SH coefficients (present only for maps that have them)."""
RGB_FIELD = "rgb"
"""Packed display colour (derived; RViz's RGB8 colour transformer reads it)."""
FISHER_PREFIX = "htrain_"
"""Prefix of the optional training-Fisher fields."""
PARAM_WIDTHS = {"means": 3, "quats": 4, "log_scales": 2, "opacity_logits": 1, "sh_dc": 3, "sh_rest": 9}
"""Float components per surfel of each SurfelMap parameter (the order of the Fisher fields)."""


def fisher_field_names(outputs: Sequence[str], param: str) -> list[str]:
    """Cloud field names of the training Fisher of ``param`` computed over rendered ``outputs``."""
    tag = f"{FISHER_PREFIX}{'+'.join(outputs)}__{param}"
    width = PARAM_WIDTHS[param]
    return [tag] if width == 1 else [f"{tag}_{i}" for i in range(width)]


def stamp_msg(stamp_ns: int) -> Any:
    """A ``builtin_interfaces/Time`` of integer nanoseconds."""
    from builtin_interfaces.msg import Time

    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


def header(stamp_ns: int, frame_id: str = MAP_FRAME_ID) -> Header:
    """A ``std_msgs/Header`` with the stamp in nanoseconds."""
    return Header(stamp=stamp_msg(stamp_ns), frame_id=frame_id)


def intrinsics_to_camera_info(intr: Intrinsics, stamp_ns: int, frame_id: str = MAP_FRAME_ID) -> CameraInfo:
    """Pinhole intrinsics as a ``sensor_msgs/CameraInfo`` (:func:`~roigsf_ros.data.bags.camera_info_fields`)."""
    fields = {k: v.tolist() if isinstance(v, np.ndarray) else v for k, v in camera_info_fields(intr).items()}
    return CameraInfo(header=header(stamp_ns, frame_id), **fields)


def _packed_rgb(colour01: np.ndarray) -> np.ndarray:
    """[N, 3] colours in [0, 1] as RViz's packed ``rgb`` float32 (bit pattern 0x00RRGGBB)."""
    c = (np.clip(colour01, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint32)
    return ((c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]).view(np.float32)


def surfel_map_to_cloud(
    surfel_map: SurfelMap,
    stamp_ns: int = 0,
    frame_id: str = MAP_FRAME_ID,
    h_train: dict[str, torch.Tensor] | None = None,
    fisher_outputs: Sequence[str] = (),
) -> PointCloud2:
    """The map as a PointCloud2 (layout in the module docstring); float32, little-endian, dense.

    ``h_train`` (the mapper's training Fisher over ``fisher_outputs``, rows aligned with the surfels)
    adds the ``htrain_`` fields, so a planner in another process needs no Fisher pass of its own.
    """
    m = surfel_map.detach().to(device="cpu", dtype=torch.float32)
    n = len(m)
    cols = [m.means.numpy(), m.quats.numpy(), m.log_scales.numpy(), m.opacity_logits.numpy()[:, None]]
    cols.append(m.sh_dc.numpy())
    names = list(BASE_FIELDS)
    if m.sh_rest is not None:
        cols.append(m.sh_rest.reshape(n, 9).numpy())
        names += SH_REST_FIELDS
    cols.append(_packed_rgb(m.colors().numpy())[:, None])
    names.append(RGB_FIELD)
    if h_train and not fisher_outputs:
        raise ValueError("surfel_map_to_cloud: h_train needs the fisher_outputs it was computed over")
    for param in PARAM_WIDTHS:
        if h_train and param in h_train:
            h = h_train[param].detach().to(device="cpu", dtype=torch.float32)
            if h.shape[0] != n:
                raise ValueError(f"surfel_map_to_cloud: h_train[{param!r}] has {h.shape[0]} rows, the map {n}")
            cols.append(h.reshape(n, PARAM_WIDTHS[param]).numpy())
            names += fisher_field_names(fisher_outputs, param)
    data = np.ascontiguousarray(np.concatenate(cols, axis=1), dtype="<f4")
    msg = PointCloud2()
    msg.header = header(stamp_ns, frame_id)
    msg.height, msg.width = 1, n
    msg.fields = [PointField(name=k, offset=4 * i, datatype=PointField.FLOAT32, count=1) for i, k in enumerate(names)]
    msg.is_bigendian = False
    msg.point_step = 4 * len(names)
    msg.row_step = msg.point_step * n
    msg.data = data.tobytes()
    msg.is_dense = True
    return msg


def cloud_to_surfel_map(msg: PointCloud2, where: str = "map cloud") -> SurfelMap:
    """The SurfelMap of a map cloud (exact inverse of :func:`surfel_map_to_cloud`); InputError names the field."""
    fields = {f.name: f for f in msg.fields}
    missing = [k for k in BASE_FIELDS if k not in fields]
    if missing:
        raise InputError(where, f"not a surfel map cloud: missing field(s) {', '.join(missing)}")
    if msg.is_bigendian:
        raise InputError(where, "big-endian clouds are not supported")
    n = int(msg.width) * int(msg.height)
    step = int(msg.point_step)
    wanted = list(BASE_FIELDS) + (list(SH_REST_FIELDS) if all(k in fields for k in SH_REST_FIELDS) else [])
    for k in wanted:
        f = fields[k]
        if f.datatype != PointField.FLOAT32 or f.count != 1:
            raise InputError(f"{where} field {k}", f"must be one FLOAT32 (datatype 7), got datatype {f.datatype}")
        if f.offset < 0 or f.offset + 4 > step:
            raise InputError(f"{where} field {k}", f"offset {f.offset} does not fit in point_step {step}")
    if int(msg.row_step) != step * int(msg.width):
        raise InputError(where, f"row_step {msg.row_step} != point_step * width = {step * int(msg.width)}")
    raw = bytes(msg.data) if not isinstance(msg.data, bytes) else msg.data
    if len(raw) != step * n:
        raise InputError(where, f"data has {len(raw)} bytes, expected point_step * width * height = {step * n}")
    rows = np.frombuffer(raw, dtype=np.uint8).reshape(n, step) if n else np.zeros((0, step), np.uint8)

    def col(k: str) -> np.ndarray:
        off = fields[k].offset
        return np.ascontiguousarray(rows[:, off : off + 4]).view("<f4").reshape(n).astype(np.float32)

    def stack(*names: str) -> np.ndarray:
        return np.stack([col(k) for k in names], axis=1) if n else np.zeros((0, len(names)), np.float32)

    arrays = {
        "means": stack("x", "y", "z"),
        "quats": stack("qw", "qx", "qy", "qz"),
        "log_scales": stack("log_scale_u", "log_scale_v"),
        "opacity_logits": stack("opacity_logit")[:, 0],
        "sh_dc": stack("sh_dc_0", "sh_dc_1", "sh_dc_2"),
    }
    if len(wanted) > len(BASE_FIELDS):
        arrays["sh_rest"] = stack(*SH_REST_FIELDS).reshape(n, 3, 3)
    for name, a in arrays.items():
        bad = ~np.isfinite(a.reshape(n, int(np.prod(a.shape[1:])))).all(axis=1)
        if bad.any():
            raise InputError(f"{where} field {name}", f"{int(bad.sum())} surfel(s) have non-finite values")
    if n and np.any(np.linalg.norm(arrays["quats"], axis=1) == 0):
        raise InputError(f"{where} field qw..qz", "zero-length rotation quaternion")
    return SurfelMap(**{k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in arrays.items()})


def cloud_h_train(msg: PointCloud2, where: str = "map cloud") -> tuple[tuple[str, ...], dict[str, torch.Tensor]] | None:
    """The training Fisher carried by a map cloud: (fisher_outputs, {param: tensor shaped like the map's}) or None.

    Call after :func:`cloud_to_surfel_map` accepted the cloud (its layout checks are not repeated).
    """
    fields = {f.name: f for f in msg.fields}
    tagged = [k for k in fields if k.startswith(FISHER_PREFIX) and "__" in k]
    if not tagged:
        return None
    tags = {k[len(FISHER_PREFIX) :].split("__", 1)[0] for k in tagged}
    if len(tags) != 1:
        raise InputError(f"{where} field {tagged[0]}", f"Fisher fields of several output sets: {sorted(tags)}")
    outputs = tuple(next(iter(tags)).split("+"))
    n = int(msg.width) * int(msg.height)
    step = int(msg.point_step)
    raw = bytes(msg.data) if not isinstance(msg.data, bytes) else msg.data
    rows = np.frombuffer(raw, dtype=np.uint8).reshape(n, step) if n else np.zeros((0, step), np.uint8)
    shapes = {"means": (3,), "quats": (4,), "log_scales": (2,), "opacity_logits": (), "sh_dc": (3,), "sh_rest": (3, 3)}
    out: dict[str, torch.Tensor] = {}
    for param, width in PARAM_WIDTHS.items():
        names = fisher_field_names(outputs, param)
        if not any(k in fields for k in names):
            continue
        cols = []
        for k in names:
            f = fields.get(k)
            if f is None:
                raise InputError(f"{where} field {k}", f"missing (the other {param} Fisher fields are present)")
            if f.datatype != PointField.FLOAT32 or f.count != 1 or f.offset < 0 or f.offset + 4 > step:
                raise InputError(f"{where} field {k}", "must be one FLOAT32 inside point_step")
            cols.append(np.ascontiguousarray(rows[:, f.offset : f.offset + 4]).view("<f4").reshape(n))
        a = np.stack(cols, axis=1).astype(np.float32) if n else np.zeros((0, width), np.float32)
        if not np.isfinite(a).all() or (a < 0).any():
            raise InputError(f"{where} field {names[0]}", "Fisher values must be finite and >= 0")
        out[param] = torch.from_numpy(np.ascontiguousarray(a.reshape(n, *shapes[param])))
    return outputs, out


def matrix_to_pose(T_wc: np.ndarray) -> Pose:
    """A ``geometry_msgs/Pose`` of a [4, 4] camera-to-world matrix."""
    T = np.asarray(T_wc, dtype=np.float64)
    pose = Pose()
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in T[:3, 3])
    q = matrix_to_quat_xyzw(T[:3, :3])
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = (float(v) for v in q)
    return pose


def pose_stamped(T_wc: np.ndarray, stamp_ns: int, frame_id: str = MAP_FRAME_ID) -> PoseStamped:
    """A ``geometry_msgs/PoseStamped`` of a [4, 4] camera-to-world matrix."""
    return PoseStamped(header=header(stamp_ns, frame_id), pose=matrix_to_pose(T_wc))


def poses_to_array(poses: Sequence[np.ndarray] | np.ndarray, stamp_ns: int, frame_id: str = MAP_FRAME_ID) -> PoseArray:
    """A ``geometry_msgs/PoseArray`` of [K, 4, 4] camera-to-world matrices."""
    return PoseArray(header=header(stamp_ns, frame_id), poses=[matrix_to_pose(T) for T in poses])


def array_to_poses(msg: PoseArray, where: str = "poses") -> np.ndarray:
    """[K, 4, 4] camera-to-world matrices of a PoseArray; InputError naming the index of a bad pose."""
    out = [pose_to_matrix(p, f"{where}[{i}]", where) for i, p in enumerate(msg.poses)]
    return np.stack(out) if out else np.zeros((0, 4, 4))


def _mesh_arrays(
    vertices: np.ndarray, triangles: np.ndarray, colours: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray | None]:
    """TRIANGLE_LIST points [3T, 3] float64 and RGBA colours [3T, 4] float32 (None without vertex colours)."""
    idx = np.asarray(triangles, dtype=np.int64).reshape(-1)
    v = np.asarray(vertices, dtype=np.float64)
    if idx.size and (idx.min() < 0 or idx.max() >= len(v)):
        raise InputError("mesh triangles", f"vertex index out of range [0, {len(v)})")
    pts = v[idx]
    if colours is None or len(colours) != len(vertices):
        return pts, None
    rgb = np.clip(np.asarray(colours, dtype=np.float64)[idx], 0.0, 1.0)
    rgba = np.concatenate([rgb, np.ones((len(idx), 1))], axis=1).astype(np.float32)
    return pts, rgba


def _mesh_marker_header(stamp_ns: int, frame_id: str) -> Marker:
    m = Marker()
    m.header = header(stamp_ns, frame_id)
    m.ns, m.id, m.type, m.action = "roigsf_mesh", 0, Marker.TRIANGLE_LIST, Marker.ADD
    m.pose.orientation.w = 1.0
    m.scale.x = m.scale.y = m.scale.z = 1.0
    m.color = ColorRGBA(r=0.8, g=0.8, b=0.8, a=1.0)
    return m


def mesh_marker(
    vertices: np.ndarray, triangles: np.ndarray, colours: np.ndarray | None, stamp_ns: int, frame_id: str = MAP_FRAME_ID
) -> Marker:
    """A ``visualization_msgs/Marker`` TRIANGLE_LIST of a mesh (vertices [V, 3] m, triangles [T, 3], colours [V, 3]).

    One Python object per point: fine for small meshes; publish large ones with :func:`mesh_marker_cdr`.
    """
    m = _mesh_marker_header(stamp_ns, frame_id)
    pts, rgba = _mesh_arrays(vertices, triangles, colours)
    m.points = [Point(x=x, y=y, z=z) for x, y, z in pts.tolist()]
    if rgba is not None:
        m.colors = [ColorRGBA(r=r, g=g, b=b, a=a) for r, g, b, a in rgba.tolist()]
    return m


_SENTINEL_POINT = np.array([-1.2345678901e-301, 2.3456789012e-302, -3.4567890123e-303], dtype="<f8")
_SENTINEL_COLOUR = np.array([0.0123456, 0.0654321, 0.0314159, 0.0271828], dtype="<f4")


def mesh_marker_cdr(
    vertices: np.ndarray, triangles: np.ndarray, colours: np.ndarray | None, stamp_ns: int, frame_id: str = MAP_FRAME_ID
) -> bytes:
    """:func:`mesh_marker` as serialized CDR bytes (``Publisher.publish`` sends them as is), built in bulk.

    A marker with one sentinel point and colour is serialized by rclpy; its point and colour sequences
    (uint32 count, then packed float64 x y z / float32 r g b a) are replaced by the mesh's arrays. Every
    field after them moves by a multiple of 8 bytes, so their CDR alignment is unchanged. The layout
    found is checked by deserializing a two-point splice; on any doubt the object path is used.
    """
    from rclpy.serialization import serialize_message

    pts, rgba = _mesh_arrays(vertices, triangles, colours)
    if len(pts) == 0:
        return serialize_message(mesh_marker(vertices, triangles, colours, stamp_ns, frame_id))
    template = _mesh_marker_header(stamp_ns, frame_id)
    x, y, z = _SENTINEL_POINT.tolist()
    r, g, b, a = _SENTINEL_COLOUR.tolist()
    template.points, template.colors = [Point(x=x, y=y, z=z)], [ColorRGBA(r=r, g=g, b=b, a=a)]
    raw = serialize_message(template)
    layout = _splice_layout(raw)
    if layout is None:
        return serialize_message(mesh_marker(vertices, triangles, colours, stamp_ns, frame_id))
    return _splice(raw, layout, pts, rgba)


def _splice(raw: bytes, layout: tuple[int, int, int], pts: np.ndarray, rgba: np.ndarray | None) -> bytes:
    p_count, p_data, c_count = layout
    n = np.uint32(len(pts)).tobytes()
    colour_part = (
        np.uint32(0).tobytes() if rgba is None else np.uint32(len(rgba)).tobytes() + rgba.astype("<f4").tobytes()
    )
    return b"".join(
        (
            raw[:p_count],
            n,
            raw[p_count + 4 : p_data],
            np.ascontiguousarray(pts, dtype="<f8").tobytes(),
            raw[p_data + 24 : c_count],
            colour_part,
            raw[c_count + 4 + 16 :],
        )
    )


def _splice_layout(raw: bytes) -> tuple[int, int, int] | None:
    """(offset of the point count, of the point data, of the colour count) in a one-point marker, verified."""
    from rclpy.serialization import deserialize_message

    p_data = raw.find(_SENTINEL_POINT.tobytes())
    c_data = raw.find(_SENTINEL_COLOUR.tobytes())
    if p_data < 8 or c_data < 4 or raw.count(_SENTINEL_POINT.tobytes()) != 1:
        return None
    one = np.uint32(1).tobytes()
    c_count = c_data - 4
    pts = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    rgba = np.array([[0.5, 0.25, 0.125, 1.0], [1.0, 0.5, 0.25, 1.0]], dtype=np.float32)
    for p_count in (p_data - 4, p_data - 8):  # 4 bytes of padding when the count is not 8-aligned + 4
        if raw[p_count : p_count + 4] != one or raw[c_count : c_count + 4] != one:
            continue
        try:
            back = deserialize_message(_splice(raw, (p_count, p_data, c_count), pts, rgba), Marker)
        except Exception:  # a wrong guess may not even parse
            continue
        ok_p = [(p.x, p.y, p.z) for p in back.points] == [tuple(r) for r in pts.tolist()]
        ok_c = [(c.r, c.g, c.b, c.a) for c in back.colors] == [tuple(r) for r in rgba.tolist()]
        if ok_p and ok_c and back.type == Marker.TRIANGLE_LIST:
            return p_count, p_data, c_count
    return None


__all__ = [
    "BASE_FIELDS",
    "FISHER_PREFIX",
    "MAP_FRAME_ID",
    "PARAM_WIDTHS",
    "RGB_FIELD",
    "SH_REST_FIELDS",
    "array_to_poses",
    "cloud_h_train",
    "cloud_to_surfel_map",
    "fisher_field_names",
    "header",
    "matrix_to_pose",
    "mesh_marker",
    "mesh_marker_cdr",
    "pose_stamped",
    "poses_to_array",
    "stamp_msg",
    "surfel_map_to_cloud",
]
