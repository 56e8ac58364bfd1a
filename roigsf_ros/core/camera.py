"""Pinhole intrinsics and camera-to-world poses (OpenCV optical axes: x right, y down, z forward).

Poses are 4x4 float64 camera-to-world matrices ``T_wc`` throughout the library, as in Replica's
``traj.txt``. Quaternions are ``(x, y, z, w)`` as in ``geometry_msgs/Quaternion``.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from roigsf_ros.core.errors import InputError, warn_once

REPLICA_DEPTH_SCALE = 6553.5
"""Replica (NICE-SLAM layout) stores depth as uint16 with metres = value / 6553.5."""


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole camera of a ``width`` x ``height`` image; ``depth_scale`` maps uint16 PNG to metres."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    depth_scale: float = REPLICA_DEPTH_SCALE

    def __post_init__(self) -> None:
        """Refuse what no image has: a size below 1 px, a focal length that is not a positive number, a NaN centre
        (a negative width failed later as numpy's "negative dimensions", a NaN focal length scored every view 0).
        """
        if not all(isinstance(v, int | np.integer) and v >= 1 for v in (self.width, self.height)):
            raise InputError(
                "intrinsics", f"width and height must be whole numbers >= 1, got {self.width}x{self.height}"
            )
        if not all(np.isfinite(v) and v > 0 for v in (self.fx, self.fy, self.depth_scale)):
            raise InputError("intrinsics", f"fx, fy and depth_scale must be finite and > 0, got fx={self.fx}, "
                             f"fy={self.fy}, depth_scale={self.depth_scale}")  # fmt: skip
        if not all(np.isfinite(v) for v in (self.cx, self.cy)):
            raise InputError("intrinsics", f"cx and cy must be finite, got cx={self.cx}, cy={self.cy}")

    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the conventional name
        """The 3x3 calibration matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def resized(self, width: int | None, height: int | None) -> Intrinsics:
        """Intrinsics of the same camera with its image resized to ``width`` x ``height``.

        Pixel centres are kept aligned (the convention of ``cv2.resize``): ``c' = (c + 0.5) s - 0.5``.
        Either side may be None: it then follows this image's aspect ratio (rounded, at least 1 px).
        """
        width, height = derive_size(width, height, (self.width, self.height))
        if width <= 0 or height <= 0:
            raise InputError("--width/--height", f"image size must be positive, got {width}x{height}")
        sx, sy = width / self.width, height / self.height
        return replace(
            self,
            width=int(width),
            height=int(height),
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5,
            cy=(self.cy + 0.5) * sy - 0.5,
        )

    def to_replica_json(self) -> dict:
        """The ``cam_params.json`` dictionary of the NICE-SLAM Replica layout."""
        return {
            "camera": {
                "w": self.width,
                "h": self.height,
                "fx": self.fx,
                "fy": self.fy,
                "cx": self.cx,
                "cy": self.cy,
                "scale": self.depth_scale,
            }
        }


MAX_IMAGE_SIDE = 8192
"""Largest image side (px) a size given by the user may reach: twice the widest RGB-D camera's colour image (Azure
Kinect, 4096 px). Larger frames do not fit in memory: one 8192 x 6144 frame's ray directions alone take 1.1 GiB
(float64), 100000 px wide 168 GiB, so they are refused up front rather than failing in numpy."""


def derive_size(width: int | None, height: int | None, default: tuple[int, int]) -> tuple[int, int]:
    """``(width, height)`` with a missing side taken from ``default``'s aspect ratio (both missing: ``default``).

    So ``--width`` alone keeps the picture's shape instead of pairing it with the default height. A given size whose
    sides exceed :data:`MAX_IMAGE_SIDE` is an InputError naming the option.
    """
    if width is None and height is None:
        return int(default[0]), int(default[1])
    if width is not None and height is not None:
        name, size = "--width/--height", (int(width), int(height))
        if min(size) <= 0:
            raise InputError(name, f"image size must be positive, got {size[0]}x{size[1]}")
    else:
        name, given = ("--height", height) if width is None else ("--width", width)
        if given <= 0:
            raise InputError(name, f"image size must be positive, got {given}")
        if width is None:
            size = max(1, round(given * default[0] / default[1])), int(given)
        else:
            size = int(given), max(1, round(given * default[1] / default[0]))
    if max(size) > MAX_IMAGE_SIDE:
        raise InputError(
            name,
            f"image size {size[0]}x{size[1]} is above {MAX_IMAGE_SIDE} px a side (twice the widest RGB-D camera's; "
            "larger frames do not fit in memory)",
        )
    return size


def load_cam_params(path: str | Path) -> Intrinsics:
    """Read a Replica ``cam_params.json`` (``{"camera": {w, h, fx, fy, cx, cy, scale}}``)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(path, "camera parameters file not found") from None
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(path, f"cannot read camera parameters: {exc}") from None
    cam = data.get("camera", data) if isinstance(data, dict) else None
    if not isinstance(cam, dict):
        raise InputError(path, "expected a JSON object with a 'camera' entry")
    missing = [k for k in ("w", "h", "fx", "fy", "cx", "cy") if k not in cam]
    if missing:
        raise InputError(path, f"missing camera field(s) {', '.join(missing)}")
    values: dict[str, float] = {}
    for key in ("w", "h", "fx", "fy", "cx", "cy", "scale"):
        value = cam.get(key, REPLICA_DEPTH_SCALE)
        try:
            if isinstance(value, bool):  # JSON true is no number, though Python reads it as 1
                raise TypeError
            values[key] = float(value)
        except (TypeError, ValueError):
            raise InputError(path, f"camera field '{key}' is not a number: {value!r}") from None
        if key in ("w", "h") and not values[key].is_integer():
            raise InputError(path, f"camera field '{key}' is not a whole number of pixels: {value!r}")
    try:
        return Intrinsics(
            width=int(values["w"]),
            height=int(values["h"]),
            fx=values["fx"],
            fy=values["fy"],
            cx=values["cx"],
            cy=values["cy"],
            depth_scale=values["scale"],
        )
    except InputError as exc:  # a number, but no camera's (Intrinsics checks them)
        raise InputError(path, f"invalid camera parameters {cam}: {exc.problem}") from None


def save_cam_params(path: str | Path, intr: Intrinsics) -> None:
    """Write ``cam_params.json`` in the Replica layout."""
    Path(path).write_text(json.dumps(intr.to_replica_json(), indent=4) + "\n")


POSE_RIGID_TOL = 1e-2
"""Largest ``|R^T R - I|`` of a pose rotation that is accepted (and re-orthonormalised).

Real-sensor trajectories (KinectFusion poses in 7-Scenes, ScanNet) are off by 1e-4 to 4e-4 from
float round-off accumulated over the sequence; a clearly non-rigid matrix is off by far more."""
MAX_POSITION_M = 10_000.0
"""Farthest a camera may be from the map origin, m. The scoring's voxel maps key +-2^20 voxels a side (+-21 km at the
default 2 cm, +-10.5 km at 1 cm): one keyframe posed in GPS/UTM metres (or after an odometry jump of that size) filled
the map with surfels no voxel could key, and every later planner request failed. Refused as the pose it is instead."""
_EXACT_TOL = 1e-9
"""Below this deviation a rotation is left as it is."""
_WARN_TOL = 1e-5
"""Above this deviation re-orthonormalising is worth a warning. Text rounding cannot reach it: a rotation printed to 6
decimals (``%f``) or more is off by at most 2 * sqrt(3) * 5e-7 = 1.7e-6 (8 decimals: 1.7e-8), where real-sensor
trajectories (and ``scene synth --sensor``) are off by 1e-4 or more."""
_log = logging.getLogger(__name__)


def _rigid_pose(T_wc: np.ndarray, where: str, tol: float) -> tuple[np.ndarray, float]:
    """``(T, deviation)``: the checked pose with its rotation projected onto SO(3), and ``|R^T R - I|`` before."""
    T = np.array(T_wc, dtype=np.float64)  # a copy: the caller's matrix is never modified
    if T.shape != (4, 4):
        raise InputError(where, f"pose must be 4x4, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise InputError(where, "pose has non-finite values")
    far = float(np.linalg.norm(T[:3, 3]))
    if far > MAX_POSITION_M:
        raise InputError(where, f"pose position {np.round(T[:3, 3], 1).tolist()} m is {far:.0f} m from the map origin, "
                         f"beyond the {MAX_POSITION_M:g} m this package maps (MAX_POSITION_M): GPS/UTM poses need a "
                         "local map frame")  # fmt: skip
    R = T[:3, :3]
    dev = float(np.abs(R.T @ R - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if abs(det) < 1e-6:  # a zero or collapsed rotation block (an all-zero pose, a missing quaternion) is no reflection
        raise InputError(where, f"pose rotation is singular (det {det:.3g}; all zero?): not a rigid transform")
    if det < 0:
        raise InputError(where, f"pose rotation has det {det:.3g} < 0 (a reflection: not a rigid transform)")
    if dev > tol:
        raise InputError(
            where, f"pose rotation is not orthonormal (|R^T R - I| = {dev:.2g} > {tol:g}: not a rigid transform)"
        )
    row_tol = min(tol, 1e-4)
    if np.abs(T[3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > row_tol:
        raise InputError(where, f"pose bottom row is {T[3].tolist()}, expected [0, 0, 0, 1]")
    T[3] = (0.0, 0.0, 0.0, 1.0)
    if dev > _EXACT_TOL:
        U, _, Vt = np.linalg.svd(R)  # nearest rotation in the Frobenius norm (det > 0 and dev < 1 keep it proper)
        T[:3, :3] = U @ Vt
    return T, dev


def check_pose(T_wc: np.ndarray, where: str, tol: float = POSE_RIGID_TOL) -> np.ndarray:
    """``T_wc`` as a float64 [4, 4] rigid transform, else InputError naming ``where``.

    A rotation within ``tol`` of orthonormal (``|R^T R - I|``) with det > 0 is re-orthonormalised
    (SVD projection to the nearest rotation) instead of refused, so real-sensor poses are accepted;
    the bottom row must be (0, 0, 0, 1) within ``min(tol, 1e-4)``. Silent: use :func:`load_pose`
    for poses read from a file, bag or message.
    """
    return _rigid_pose(T_wc, where, tol)[0]


def load_pose(T_wc: np.ndarray, where: str, source: str | None = None) -> np.ndarray:
    """A pose read from outside (``traj.txt`` line, bag, message): :func:`check_pose`, and one warning per source.

    Every pose loader goes through here. ``where`` names the line or message in errors; ``source``
    (the file or topic, default ``where``) is named in a single logged warning when its poses needed
    re-orthonormalising beyond what printing them to 6+ decimals explains (``_WARN_TOL``), not one per frame.
    """
    T, dev = _rigid_pose(T_wc, where, POSE_RIGID_TOL)
    key = source if source is not None else where
    if dev > _WARN_TOL:
        warn_once(
            _log,
            key,
            "not orthonormal",
            "%s: pose rotations are not exactly orthonormal (|R^T R - I| = %.2g at %s); re-orthonormalised "
            "(nearest rotation), further ones from this source silently",
            key,
            dev,
            where,
        )
    return T


def matrix_to_quat_xyzw(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w), w >= 0, of a 3x3 rotation matrix (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    t = np.trace(R)
    if t > 0:
        s = 2.0 * np.sqrt(t + 1.0)
        q = np.array([(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s])
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = np.array([0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s])
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = np.array([(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s])
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = np.array([(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s])
    q /= np.linalg.norm(q)
    return q if q[3] >= 0 else -q


def quat_xyzw_to_matrix(q: np.ndarray, where: str = "quaternion") -> np.ndarray:
    """3x3 rotation of a quaternion (x, y, z, w); it must be finite and of norm within 1e-3 of 1."""
    q = np.asarray(q, dtype=np.float64)
    n = float(np.linalg.norm(q))
    if q.shape != (4,) or not np.all(np.isfinite(q)) or abs(n - 1.0) > 1e-3:
        raise InputError(where, f"quaternion {q.tolist()} is not a finite unit quaternion")
    x, y, z, w = q / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def pose_from_position_quat(position: np.ndarray, quat_xyzw: np.ndarray, where: str = "pose") -> np.ndarray:
    """4x4 camera-to-world from a position and an (x, y, z, w) quaternion."""
    p = np.asarray(position, dtype=np.float64)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise InputError(where, f"position {p.tolist()} is not 3 finite numbers")
    T = np.eye(4)
    T[:3, :3] = quat_xyzw_to_matrix(quat_xyzw, where)
    T[:3, 3] = p
    return T


def depth_points_w(depth_m: np.ndarray, T_wc: np.ndarray, intr: Intrinsics, valid: np.ndarray) -> np.ndarray:
    """World points [N, 3] float64 (metres) of the ``valid`` pixels [H, W] of a z-depth image [H, W] at ``T_wc``."""
    depth = np.asarray(depth_m, dtype=np.float64)
    if depth.shape != (intr.height, intr.width) or np.shape(valid) != depth.shape:
        raise InputError(
            "depth_m", f"shape {depth.shape} (mask {np.shape(valid)}) does not match the camera's "
            f"{intr.height}x{intr.width}"
        )  # fmt: skip
    T = check_pose(T_wc, "T_wc")
    v, u = np.nonzero(valid)
    z = depth[v, u]
    cam = np.stack([(u - intr.cx) / intr.fx * z, (v - intr.cy) / intr.fy * z, z], axis=1)
    return cam @ T[:3, :3].T + T[:3, 3]


__all__ = [
    "MAX_POSITION_M",
    "POSE_RIGID_TOL",
    "REPLICA_DEPTH_SCALE",
    "Intrinsics",
    "check_pose",
    "depth_points_w",
    "derive_size",
    "load_cam_params",
    "load_pose",
    "matrix_to_quat_xyzw",
    "pose_from_position_quat",
    "quat_xyzw_to_matrix",
    "save_cam_params",
]
