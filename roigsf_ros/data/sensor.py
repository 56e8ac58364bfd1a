"""A simulated structured-light RGB-D sensor (Kinect v1 style): what a real camera does to ideal renders.

No real Kinect/RealSense sequence is available to this project, so real-sensor data is simulated:
an ideal ray-cast frame (:class:`roigsf_ros.data.scene.MeshRenderer`) goes through this model, and
the result is written in the Replica layout with the poses as a KinectFusion-style tracker writes
them, so that it goes through the same loaders as a real sequence. Everything is seeded: the same
seed gives the same images and poses, frame by frame (each frame draws from its own stream).

Depth (in this order, on the ideal z-depth ``z`` and the incidence angle ``theta`` between the ray
and the surface normal):

1. **Holes** (depth 0), each cause counted separately in :class:`HoleCounts`:
   no return outside ``[min_range_m, max_range_m]`` (Kinect v1: 0.4 m in near mode, about 4 m);
   grazing incidence ``theta > max_incidence_deg`` (the speckle pattern does not come back);
   **projector shadow**: a surface point the IR projector, ``baseline_m`` beside the camera, does
   not see (occluded by a nearer surface in the same image row). This is the exact rectified-stereo
   occlusion test, so the band left of a foreground edge is as wide as the disparity difference
   ``f b (1/z_fg - 1/z_bg)`` px (about 20 px at 640 px for 1 m in front of 2 m), on the side away
   from the projector; and random **speckle dropouts** (``dropout_prob`` of the pixels).
2. **Lateral noise** at depth edges (Nguyen et al. 2012, Eq. 4): ``sigma_L = 0.8 + 0.035 theta /
   (pi/2 - theta)`` px (of the native sensor); each pixel within one pixel of an edge (a neighbour
   more than ``edge_jump_rel`` of its depth away, or a hole) takes the depth of a neighbour drawn
   at a Gaussian offset, so edges come out jagged.
3. **Axial noise** (Nguyen, Izadi, Lovell, "Modeling Kinect Sensor Noise for Improved 3D
   Reconstruction and Tracking", 3DIMPVT 2012, Eq. 8-9): Gaussian with ``sigma_z = 0.0012 +
   0.0019 (z - 0.4)^2`` m, plus ``0.0001 / sqrt(z) * theta^2 / (pi/2 - theta)^2`` for ``theta >
   60 deg``.
4. **Disparity quantisation** (Khoshelham and Elberink 2012; Smisek et al. 2011): Kinect v1
   reports disparity ``d = f b / z`` in 1/8 px steps, so depth takes the values ``f b / (k / 8)``;
   the step grows as ``z^2 / (8 f b)`` (about 1.3 cm at 2 m with f = 525 px, b = 7.5 cm).

``f`` is the camera's ``fx`` at ``native_width_px`` (the sensor's own resolution): a render at
another size simulates the same sensor (same quantisation in metres, same lateral noise in native
pixels), and a 640x480 render is the sensor itself.

Colour: additive Gaussian noise (``colour_sigma`` in 8-bit levels), then a JPEG round trip at
``jpeg_quality`` (what a compressed image transport or a recorded dataset stores).

Poses, as KinectFusion-style trackers write them (7-Scenes, ScanNet): each rotation is multiplied
by ``I + E`` with a random 3x3 ``E`` scaled so that ``|R^T R - I|`` (max abs entry) is uniform in
``[pose_ortho_dev_min, pose_ortho_dev_max]`` (1e-4 to 4e-4, as measured on those datasets), so the
loader must re-orthonormalise them (:func:`roigsf_ros.core.camera.load_pose`); and, optionally, a
random-walk **drift** of the camera position and orientation whose standard deviation grows with
the square root of the path length (``drift_trans_m_per_sqrt_m``, ``drift_rot_deg_per_sqrt_m``;
off by default).

What it does not capture (a real sequence has these): calibration error between the depth and
colour cameras and in the intrinsics, depth-to-colour registration and its timing, rolling
shutter, motion blur, auto exposure and white balance, IR interference (sunlight, other sensors),
multi-path and material effects (dark, specular, transparent surfaces), temporal correlation of
the noise, and real tracking drift.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from roigsf_ros.core.camera import Intrinsics, check_pose, load_cam_params
from roigsf_ros.core.config import Config
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.frame import Frame

KINECT_V1_INTRINSICS = Intrinsics(width=640, height=480, fx=525.0, fy=525.0, cx=319.5, cy=239.5)
"""The Kinect v1 colour camera at 640x480: fx = fy = 525, principal point at the centre (the
default calibration of the ROS openni driver, which TUM RGB-D's docs give as its ROS default)."""

CAMERAS = {"kinect-v1": KINECT_V1_INTRINSICS}
"""Named cameras, for ``--cam NAME`` (:func:`load_camera`)."""


def load_camera(cam: str | Path) -> Intrinsics:
    """A camera given as a ``cam_params.json`` path or as a name in :data:`CAMERAS` (a file of that name wins).

    One rule for every ``--cam`` / ``cam=``: ``roigsf scene render`` took ``kinect-v1`` while ``roigsf map`` read it
    as a file name and said "camera parameters file not found".
    """
    if not Path(cam).exists() and str(cam) in CAMERAS:
        return CAMERAS[str(cam)]
    try:
        return load_cam_params(cam)
    except InputError as exc:
        if Path(cam).exists() or "/" in str(cam) or str(cam).endswith(".json"):
            raise
        raise InputError(exc.where, f"{exc.problem}, nor a named camera ({', '.join(sorted(CAMERAS))})") from None


_STREAM_DEPTH, _STREAM_COLOUR, _STREAM_POSE, _STREAM_DRIFT = 1, 2, 3, 4


@dataclass(frozen=True)
class SensorConfig(Config):
    """Every constant of the simulated sensor (defaults: a Kinect v1 at 640x480; sources in the module doc)."""

    native_width_px: int = 640
    """Width of the sensor's own images: disparity, quantisation and lateral noise are in its pixels."""
    axial_a_m: float = 0.0012
    """Constant term of the axial noise std (Nguyen et al. 2012)."""
    axial_b_m_per_m2: float = 0.0019
    """Quadratic term of the axial noise std: ``a + b (z - z0)^2`` (Nguyen et al. 2012)."""
    axial_z0_m: float = 0.4
    """Depth of the quadratic term's minimum (Nguyen et al. 2012)."""
    axial_angle_term: bool = True
    """Add Nguyen's ``0.0001 / sqrt(z) * theta^2 / (pi/2 - theta)^2`` beyond 60 deg incidence."""
    lateral_px: float = 0.8
    """Lateral noise std at edges, native px, at normal incidence (Nguyen et al. 2012)."""
    lateral_angle_coeff: float = 0.035
    """Lateral noise growth with incidence: ``lateral_px + c * theta / (pi/2 - theta)`` (Nguyen et al. 2012)."""
    edge_jump_rel: float = 0.02
    """A neighbour whose depth differs by more than this fraction of the pixel's depth makes an edge."""
    baseline_m: float = 0.075
    """Projector-camera baseline (Kinect v1: 7.5 cm)."""
    disparity_step_px: float = 0.125
    """Disparity quantisation step in native px (Kinect v1: 1/8 px); 0 turns quantisation off."""
    projector_side: int = 1
    """+1: projector on the camera's +x (right) side, so shadows fall left of foreground edges; -1: the
    other side; 0: no projector shadows."""
    min_range_m: float = 0.4
    """No return nearer than this (Kinect v1 near mode; 0.8 m in default mode)."""
    max_range_m: float = 4.0
    """No return beyond this (Kinect v1's practical range)."""
    max_incidence_deg: float = 75.0
    """No return where the angle between the ray and the surface normal exceeds this."""
    dropout_prob: float = 0.01
    """Fraction of pixels lost at random (speckle dropouts)."""
    colour_sigma: float = 2.0
    """Std of additive colour noise, in 8-bit levels."""
    jpeg_quality: int = 80
    """Quality of the colour JPEG round trip (0: none)."""
    pose_ortho_dev_min: float = 1e-4
    """Least ``|R^T R - I|`` (max abs entry) of a written pose's rotation."""
    pose_ortho_dev_max: float = 4e-4
    """Largest ``|R^T R - I|`` of a written pose's rotation (0 and 0: exact rotations)."""
    drift_trans_m_per_sqrt_m: float = 0.0
    """Random-walk position drift: std of the accumulated error after L metres of path is this * sqrt(L)."""
    drift_rot_deg_per_sqrt_m: float = 0.0
    """Random-walk orientation drift: std per axis after L metres of path is this * sqrt(L) degrees."""

    def validate(self) -> SensorConfig:
        """Self, or InputError naming the first field out of range."""
        nonneg = (
            "axial_a_m", "axial_b_m_per_m2", "axial_z0_m", "lateral_px", "lateral_angle_coeff", "edge_jump_rel",
            "disparity_step_px", "min_range_m", "colour_sigma", "pose_ortho_dev_min", "pose_ortho_dev_max",
            "drift_trans_m_per_sqrt_m", "drift_rot_deg_per_sqrt_m",
        )  # fmt: skip
        for name in nonneg:
            value = float(getattr(self, name))
            if not math.isfinite(value) or value < 0:
                raise InputError(name, f"must be a finite number >= 0, got {getattr(self, name)}")
        if int(self.native_width_px) < 1:
            raise InputError("native_width_px", f"must be >= 1, got {self.native_width_px}")
        if not (math.isfinite(self.baseline_m) and self.baseline_m > 0):
            raise InputError("baseline_m", f"must be a positive number, got {self.baseline_m}")
        if not math.isfinite(self.max_range_m):
            raise InputError("max_range_m", f"must be a finite number, got {self.max_range_m}")
        if self.max_range_m <= self.min_range_m:  # either may be the one set: name both
            raise InputError(
                "min_range_m, max_range_m",
                f"min_range_m must be below max_range_m, got {self.min_range_m} and {self.max_range_m}",
            )
        if not 0 < self.max_incidence_deg <= 90:
            raise InputError("max_incidence_deg", f"must be in (0, 90], got {self.max_incidence_deg}")
        if not 0 <= self.dropout_prob < 1:
            raise InputError("dropout_prob", f"must be in [0, 1), got {self.dropout_prob}")
        if self.projector_side not in (-1, 0, 1):
            raise InputError("projector_side", f"must be -1, 0 or 1, got {self.projector_side}")
        if not 0 <= int(self.jpeg_quality) <= 100:
            raise InputError("jpeg_quality", f"must be in 0..100 (0: no JPEG), got {self.jpeg_quality}")
        if self.pose_ortho_dev_max > 1e-2:
            raise InputError("pose_ortho_dev_max", f"must be at most 1e-2 (the loader's tolerance), got "
                             f"{self.pose_ortho_dev_max}")  # fmt: skip
        if self.pose_ortho_dev_max < self.pose_ortho_dev_min:  # either may be the one set: name both
            raise InputError(
                "pose_ortho_dev_min, pose_ortho_dev_max",
                f"pose_ortho_dev_min must be at most pose_ortho_dev_max, got {self.pose_ortho_dev_min} and "
                f"{self.pose_ortho_dev_max}",
            )
        return self


SENSORS = {"kinect": SensorConfig()}
"""Named sensor models, for ``roigsf scene render/synth --sensor NAME``."""


@dataclass
class HoleCounts:
    """Depth pixels lost, by cause (a pixel may have several causes; ``total`` counts it once)."""

    pixels: int = 0
    """Pixels looked at."""
    no_surface: int = 0
    """The ideal render hit nothing (not a sensor effect)."""
    out_of_range: int = 0
    grazing: int = 0
    shadow: int = 0
    dropout: int = 0
    not_storable: int = 0
    """Measured depths the camera's uint16 image cannot hold (above ``65535 / depth_scale`` m or rounding to 0),
    stored as holes: only huge noise or a range beyond the format's makes them."""
    total: int = 0
    """Pixels with depth 0 in the output (including ``no_surface``)."""
    by_frame: list[float] = field(default_factory=list)
    """Fraction of each frame's pixels that are holes."""

    def add(self, other: HoleCounts) -> None:
        """Accumulate another frame's counts."""
        for name in ("pixels", "no_surface", "out_of_range", "grazing", "shadow", "dropout", "not_storable", "total"):
            setattr(self, name, getattr(self, name) + getattr(other, name))
        self.by_frame.extend(other.by_frame)

    def fractions(self) -> dict[str, float]:
        """Each count as a fraction of the pixels looked at."""
        n = max(self.pixels, 1)
        names = ("no_surface", "out_of_range", "grazing", "shadow", "dropout", "not_storable", "total")
        return {name: getattr(self, name) / n for name in names}


# ------------------------------------------------------------------------------------------ depth
def axial_sigma_m(z: np.ndarray, theta: np.ndarray | float = 0.0, config: SensorConfig | None = None) -> np.ndarray:
    """Axial (along the ray) noise std in metres at depth ``z`` and incidence ``theta`` (rad): Nguyen et al. 2012."""
    c = config or SensorConfig()
    z = np.asarray(z, dtype=np.float64)
    sigma = c.axial_a_m + c.axial_b_m_per_m2 * (z - c.axial_z0_m) ** 2
    if c.axial_angle_term:
        theta = np.minimum(np.asarray(theta, dtype=np.float64), np.deg2rad(89.0))
        steep = theta > np.deg2rad(60.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            extra = 0.0001 / np.sqrt(np.maximum(z, 1e-6)) * theta**2 / (np.pi / 2 - theta) ** 2
        sigma = sigma + np.where(steep, extra, 0.0)
    return sigma


def lateral_sigma_px(theta: np.ndarray | float, config: SensorConfig | None = None) -> np.ndarray:
    """Lateral noise std in native px at incidence ``theta`` (rad): Nguyen et al. 2012."""
    c = config or SensorConfig()
    theta = np.minimum(np.asarray(theta, dtype=np.float64), np.deg2rad(89.0))
    return c.lateral_px + c.lateral_angle_coeff * theta / (np.pi / 2 - theta)


def quantise_disparity(z: np.ndarray, f_px: float, baseline_m: float, step_px: float) -> np.ndarray:
    """Depth ``z`` (m; 0 stays 0) as the sensor reports it: disparity ``f b / z`` rounded to ``step_px`` steps."""
    z = np.asarray(z, dtype=np.float64)
    if step_px <= 0:
        return z.copy()
    fb = f_px * baseline_m
    out = np.zeros_like(z)
    ok = z > 0
    d = np.maximum(np.round(fb / z[ok] / step_px), 1.0) * step_px
    out[ok] = fb / d
    return out


def projector_shadow(depth_m: np.ndarray, fx: float, baseline_m: float, side: int = 1) -> np.ndarray:
    """Bool [H, W]: pixels whose surface point the projector (``side * baseline_m`` along camera x) cannot see.

    Rectified-stereo occlusion: with the projector at ``+b`` a pixel ``u`` of disparity ``d(u) = fx b / z``
    projects to projector column ``u - d(u)``; it is lit iff that column is less than every column of the
    pixels right of it in its row (a pixel right of it with a column at or left of its own is a nearer surface
    on the same projector ray). Pixels without depth (0) neither cast nor receive shadows.
    """
    z = np.asarray(depth_m, dtype=np.float64)
    if side == 0:
        return np.zeros(z.shape, dtype=bool)
    if side < 0:  # mirror the image: the projector on the other side is the same test
        return projector_shadow(z[:, ::-1], fx, baseline_m, 1)[:, ::-1]
    w = z.shape[1]
    valid = z > 0
    with np.errstate(divide="ignore"):
        col = np.where(valid, np.arange(w, dtype=np.float64)[None, :] - fx * baseline_m / z, np.inf)
    # Minimum projector column strictly to the right of each pixel.
    suffix = np.minimum.accumulate(col[:, ::-1], axis=1)[:, ::-1]
    right_min = np.full_like(col, np.inf)
    right_min[:, :-1] = suffix[:, 1:]
    return valid & (col >= right_min)


def depth_edges(depth_m: np.ndarray, jump_rel: float) -> np.ndarray:
    """Bool [H, W]: pixels with a 4-neighbour whose depth differs by more than ``jump_rel`` of theirs, or is a hole.

    Only pixels with depth are marked (a hole next to a surface is not an edge pixel; the surface pixel is).
    """
    z = np.asarray(depth_m, dtype=np.float64)
    valid = z > 0
    edge = np.zeros(z.shape, dtype=bool)
    for axis in (0, 1):
        a = np.moveaxis(z, axis, 0)
        jump = np.abs(a[1:] - a[:-1]) > jump_rel * np.maximum(a[1:], a[:-1])
        pair = jump | ((a[1:] > 0) != (a[:-1] > 0))
        e = np.moveaxis(edge, axis, 0)
        e[1:] |= pair
        e[:-1] |= pair
    return edge & valid


def _frame_rng(seed: int, index: int, stream: int) -> np.random.Generator:
    """The generator of one frame's ``stream`` (depth, colour, pose): independent of the order frames come in."""
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, int(index) & 0xFFFFFFFF, stream, 0x5E4502])


def simulate_depth(
    depth_m: np.ndarray,
    cos_incidence: np.ndarray | None,
    intr: Intrinsics,
    rng: np.random.Generator,
    config: SensorConfig | None = None,
) -> tuple[np.ndarray, HoleCounts]:
    """The sensor's depth [H, W] float32 (0: hole) from ideal z-depth ``depth_m`` (0: no surface), and its holes.

    ``cos_incidence`` [H, W] is ``|cos|`` of the angle between each ray and the surface normal (None:
    normal incidence everywhere, e.g. for a depth image without geometry). ``intr`` is the render's camera; a
    measured depth its uint16 depth image (``intr.depth_scale``) cannot hold becomes a hole, as it would in the file.
    """
    c = config or SensorConfig()
    z = np.asarray(depth_m, dtype=np.float64)
    if z.shape != (intr.height, intr.width):
        raise InputError("depth_m", f"shape {z.shape} does not match the camera's {intr.width}x{intr.height}")
    cos_i = np.ones_like(z) if cos_incidence is None else np.clip(np.asarray(cos_incidence, np.float64), 0.0, 1.0)
    theta = np.arccos(cos_i)
    scale = intr.width / c.native_width_px  # render px per native px
    surface = np.isfinite(z) & (z > 0)
    z = np.where(surface, z, 0.0)

    holes = HoleCounts(pixels=int(z.size), no_surface=int((~surface).sum()))
    out_of_range = surface & ((z < c.min_range_m) | (z > c.max_range_m))
    grazing = surface & (theta > np.deg2rad(c.max_incidence_deg))
    shadow = projector_shadow(z, intr.fx, c.baseline_m, c.projector_side)  # nearer surfaces cast shadows at any range
    holes.out_of_range, holes.grazing, holes.shadow = int(out_of_range.sum()), int(grazing.sum()), int(shadow.sum())
    meas = np.where(out_of_range | grazing | shadow, 0.0, z)

    # Lateral noise: edge pixels take the depth of a neighbour at a Gaussian offset (native px scaled to render px).
    edge = depth_edges(meas, c.edge_jump_rel)
    if c.lateral_px > 0 and edge.any():
        vs, us = np.nonzero(edge)
        sig = lateral_sigma_px(theta[vs, us], c) * scale
        du = np.rint(rng.normal(size=len(us)) * sig).astype(np.int64)
        dv = np.rint(rng.normal(size=len(vs)) * sig).astype(np.int64)
        src_u = np.clip(us + du, 0, intr.width - 1)
        src_v = np.clip(vs + dv, 0, intr.height - 1)
        jittered = meas.copy()
        jittered[vs, us] = meas[src_v, src_u]
        meas = jittered
    ok = meas > 0
    # Axial noise (the source pixel's incidence is close enough to its own), then disparity quantisation.
    meas[ok] += rng.normal(size=int(ok.sum())) * axial_sigma_m(meas[ok], theta[ok], c)
    meas = np.where(meas > 0, meas, 0.0)
    f_native = intr.fx / scale
    meas = quantise_disparity(meas, f_native, c.baseline_m, c.disparity_step_px)
    if c.dropout_prob > 0:
        drop = rng.random(z.shape) < c.dropout_prob
        holes.dropout = int((drop & (meas > 0)).sum())
        meas[drop] = 0.0
    # What the uint16 depth image at the camera's scale cannot hold is a hole in the file: count it here, so the
    # holes reported are the holes written (write_replica stores such depths as 0).
    units = meas * intr.depth_scale
    not_storable = (meas > 0) & ((units > 65535) | (np.round(units) < 1))
    holes.not_storable = int(not_storable.sum())
    meas[not_storable] = 0.0
    holes.total = int((meas <= 0).sum())
    holes.by_frame.append(holes.total / max(holes.pixels, 1))
    return meas.astype(np.float32), holes


# ----------------------------------------------------------------------------------------- colour
def simulate_colour(rgb: np.ndarray, rng: np.random.Generator, config: SensorConfig | None = None) -> np.ndarray:
    """The sensor's colour [H, W, 3] uint8 RGB: Gaussian noise, then a JPEG round trip."""
    c = config or SensorConfig()
    img = np.asarray(rgb)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise InputError("rgb", f"expected [H, W, 3] uint8, got {img.dtype} {img.shape}")
    if c.colour_sigma > 0:
        noisy = img.astype(np.float64) + rng.normal(scale=c.colour_sigma, size=img.shape)
        img = np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
    if c.jpeg_quality > 0:
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, c.jpeg_quality])
        if not ok:
            raise RuntimeError("OpenCV could not encode a JPEG")
        img = cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    return img


# ------------------------------------------------------------------------------------------ poses
def orthonormality_error(R: np.ndarray) -> float:
    """``max |R^T R - I|`` of a 3x3 matrix (what :func:`roigsf_ros.core.camera.load_pose` tolerates up to 1e-2)."""
    R = np.asarray(R, dtype=np.float64)
    return float(np.abs(R.T @ R - np.eye(3)).max())


def non_orthonormal(R: np.ndarray, deviation: float, rng: np.random.Generator) -> np.ndarray:
    """``R (I + E)`` with a random 3x3 ``E`` scaled so that :func:`orthonormality_error` is ``deviation``.

    ``E`` has a symmetric part (the stretch that makes it non-orthonormal, as accumulated float
    round-off does) and an antisymmetric part of the same size (a rotation error of about ``deviation``
    rad, i.e. 0.02 deg at 4e-4).
    """
    R = np.asarray(R, dtype=np.float64)
    if deviation <= 0:
        return R.copy()
    E = rng.normal(size=(3, 3))
    dev1 = orthonormality_error(np.eye(3) + 1e-6 * E) / 1e-6  # first-order deviation per unit scale
    s = deviation / max(dev1, 1e-12)
    for _ in range(3):  # the quadratic term is ~1e-4 relative: a few secant steps make it exact
        s *= deviation / orthonormality_error(np.eye(3) + s * E)
    return R @ (np.eye(3) + s * E)


def _rotvec_to_matrix(w: np.ndarray) -> np.ndarray:
    """Rodrigues: the rotation of axis-angle vector ``w`` (rad)."""
    th = float(np.linalg.norm(w))
    if th < 1e-15:
        return np.eye(3)
    k = w / th
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * K @ K


def measured_poses(poses: np.ndarray, seed: int, config: SensorConfig | None = None) -> np.ndarray:
    """The poses [N, 4, 4] as the simulated tracker writes them: optional random-walk drift, then non-orthonormal.

    Drift: the error in position and orientation (about the camera centre) is a random walk whose
    increments over a step of ``s`` metres have std ``drift * sqrt(s)``. Each rotation is then multiplied
    by ``I + E`` (:func:`non_orthonormal`) with a deviation drawn uniformly in the configured range.
    Deterministic for ``seed``; each pose's non-orthonormality comes from its own stream.
    """
    c = config or SensorConfig()
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    for i, T in enumerate(poses):
        check_pose(T, f"pose {i}")
    out = poses.copy()
    drift_rng = _frame_rng(seed, 0, _STREAM_DRIFT)
    err_t, err_R = np.zeros(3), np.eye(3)
    rot_std = np.deg2rad(c.drift_rot_deg_per_sqrt_m)
    for i in range(len(poses)):
        if i > 0 and (c.drift_trans_m_per_sqrt_m > 0 or rot_std > 0):
            step = math.sqrt(float(np.linalg.norm(poses[i, :3, 3] - poses[i - 1, :3, 3])))
            err_t = err_t + drift_rng.normal(scale=c.drift_trans_m_per_sqrt_m * step, size=3)
            err_R = _rotvec_to_matrix(drift_rng.normal(scale=rot_std * step, size=3)) @ err_R
        R = err_R @ poses[i, :3, :3]
        rng = _frame_rng(seed, i, _STREAM_POSE)
        dev = rng.uniform(c.pose_ortho_dev_min, c.pose_ortho_dev_max)
        out[i, :3, :3] = non_orthonormal(R, dev, rng)
        out[i, :3, 3] = poses[i, :3, 3] + err_t
    return out


# ---------------------------------------------------------------------------------------- frames
class SensorModel:
    """A seeded simulated sensor: :meth:`frame` turns an ideal frame into the sensor's, :meth:`poses` the poses.

    Holes of every frame seen are accumulated in :attr:`holes`.
    """

    def __init__(self, config: SensorConfig | None = None, seed: int = 0, name: str = "custom") -> None:
        self.config = config or SensorConfig()
        self.seed = int(seed)
        self.name = name
        self.holes = HoleCounts()

    @classmethod
    def named(cls, name: str, seed: int = 0, **overrides: object) -> SensorModel:
        """One of :data:`SENSORS` (e.g. ``"kinect"``), with fields of :class:`SensorConfig` overridden."""
        if name not in SENSORS:
            raise InputError("--sensor", f"unknown sensor {name!r}; known: {', '.join(sorted(SENSORS))}")
        base = SENSORS[name].to_dict()
        unknown = sorted(set(overrides) - set(base))
        if unknown:
            raise InputError("--sensor-set", f"unknown sensor parameter(s) {', '.join(unknown)}")
        return cls(SensorConfig.from_dict(base | overrides), seed=seed, name=name)

    def frame(self, frame: Frame, intr: Intrinsics, cos_incidence: np.ndarray | None = None) -> Frame:
        """The sensor's view of an ideal ``frame`` (same index and pose): noisy depth with holes, noisy JPEG colour."""
        depth, holes = simulate_depth(
            frame.depth_m, cos_incidence, intr, _frame_rng(self.seed, frame.index, _STREAM_DEPTH), self.config
        )
        self.holes.add(holes)
        rgb = simulate_colour(frame.rgb, _frame_rng(self.seed, frame.index, _STREAM_COLOUR), self.config)
        return Frame(index=frame.index, rgb=rgb, depth_m=depth, T_wc=frame.T_wc)

    def poses(self, poses: np.ndarray) -> np.ndarray:
        """The poses as the sensor's tracker writes them (:func:`measured_poses`)."""
        return measured_poses(poses, self.seed, self.config)

    def describe(self) -> dict[str, object]:
        """Name, seed, every constant and the hole fractions so far (for ``render.json``)."""
        return {
            "name": self.name,
            "seed": self.seed,
            "config": self.config.to_dict(),
            "hole_fractions": self.holes.fractions(),
            "simulated": "a sensor model applied to ideal renders, not real sensor data (see roigsf_ros.data.sensor)",
        }


__all__ = [
    "CAMERAS",
    "KINECT_V1_INTRINSICS",
    "SENSORS",
    "HoleCounts",
    "SensorConfig",
    "SensorModel",
    "axial_sigma_m",
    "depth_edges",
    "lateral_sigma_px",
    "load_camera",
    "measured_poses",
    "non_orthonormal",
    "orthonormality_error",
    "projector_shadow",
    "quantise_disparity",
    "simulate_colour",
    "simulate_depth",
]
