"""Ground-truth scenes: ray-cast RGB-D rendering of triangle meshes, and a procedural test room.

Meshes are ray-cast with open3d's ``RaycastingScene`` at camera-to-world poses ``T_wc`` (OpenCV
optical axes: x right, y down, z forward). Depth is z-depth along the optical axis in metres, as
Replica stores it; rays go through pixel centres, so integer pixel coordinates ``(u, v)`` are
pixel centres (``cx = 599.5`` is the middle of a 1200 px wide image).

Colour is the mesh's vertex colour, interpolated barycentrically at the hit, times a deterministic
procedural surface texture evaluated at the 3D hit point. The texture is view-independent (a
property of the surface, not of the camera), so photometric consistency across views holds; it
exists because Replica's decimated vertex colours are too smooth for photometric Fisher
information to mean anything.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import open3d as o3d
from tqdm import tqdm

from roigsf_ros.core.camera import Intrinsics, check_pose
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.fileio import atomic_dir
from roigsf_ros.core.frame import Frame
from roigsf_ros.data.replica import SCENE_MARKS, save_traj, write_replica
from roigsf_ros.data.sensor import SensorModel, orthonormality_error

ROOM_MIN = np.array([-2.5, -2.0, 0.0])
"""Lower corner (m) of the room made by :func:`synth_room` (world z up, floor at z = 0)."""
ROOM_MAX = np.array([2.5, 2.0, 2.7])
"""Upper corner (m) of the room made by :func:`synth_room`."""

_DEFAULT_GREY = 0.7  # colour of meshes without vertex colours

REPLICA_PIXEL_OFFSET = 0.5
"""``pixel_offset`` that reproduces the real Replica (NICE-SLAM) renders with their published intrinsics.

Ray-casting office0's mesh at its real poses matches the real depth to a median 0.18 mm when
pixel ``u`` is sampled at ``u + 0.5`` (the renderer's pixel-corner convention applied to
``cx = 599.5``), against 1.4 mm at ``u``; i.e. the published ``cx, cy`` are half a pixel off for
an integer-centre reader. Synthetic sequences use 0 so that their ``cam_params.json`` is exact.
"""


# --------------------------------------------------------------------------------------------
# Mesh input
# --------------------------------------------------------------------------------------------


def _ply_element_counts(path: Path) -> dict[str, int]:
    """The element counts (``vertex``, ``face``, ...) a PLY file's header declares; empty for another format.

    Open3D reads a truncated PLY up to the break and only prints a warning: the counts tell a part from the whole.
    """
    with path.open("rb") as f:
        head = f.read(65536)
    if not head.startswith(b"ply"):
        return {}
    counts: dict[str, int] = {}
    for line in head.split(b"end_header", 1)[0].splitlines():
        words = line.split()
        if len(words) == 3 and words[0] == b"element" and words[2].isdigit():
            counts[words[1].decode("ascii", "replace")] = int(words[2])
    return counts


def load_mesh(path: str | Path) -> o3d.geometry.TriangleMesh:
    """Read a triangle mesh (PLY/OBJ/...); InputError naming the file if missing, unreadable or empty.

    Open3D's own warnings ("Read PLY failed", "appears to be a PointCloud") are kept out of the output, the InputError
    saying it; the PLY parser's "RPly: ..." lines are printed by its C code and stay.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "mesh file not found")
    try:
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            mesh = o3d.io.read_triangle_mesh(str(path))
    except (OSError, RuntimeError) as exc:
        raise InputError(path, f"cannot read mesh: {exc}") from None
    if len(mesh.triangles) == 0:
        raise InputError(path, "mesh has no triangles (unreadable or not a triangle mesh)")
    declared = _ply_element_counts(path)
    read = {"vertex": len(mesh.vertices), "face": len(mesh.triangles)}  # a quad face reads as two triangles
    for element, count in read.items():
        if count < declared.get(element, 0):
            raise InputError(path, f"truncated or corrupt: {count} of the {declared[element]} {element} elements "
                             "its header declares were read")  # fmt: skip
    vertices = np.asarray(mesh.vertices)
    if not np.all(np.isfinite(vertices)):
        raise InputError(path, "mesh has non-finite vertex coordinates")
    return mesh


# --------------------------------------------------------------------------------------------
# Procedural texture
# --------------------------------------------------------------------------------------------


def _mix32(h: np.ndarray) -> np.ndarray:
    """Avalanche a uint32 array (the 'lowbias32' integer hash finaliser)."""
    h = h ^ (h >> np.uint32(16))
    h = h * np.uint32(0x7FEB352D)
    h = h ^ (h >> np.uint32(15))
    h = h * np.uint32(0x846CA68B)
    return h ^ (h >> np.uint32(16))


def _value_noise(pt: np.ndarray, salt: int, channels: int = 1) -> np.ndarray:
    """``channels`` (1-3) independent channels of smooth lattice value noise at points ``pt`` [3, N]: [C, N] in [0, 1].

    Each lattice corner's value comes from an integer hash of its coordinates and ``salt`` (no RNG
    state); corners are blended trilinearly with smoothstep weights, so the noise is C1 continuous.
    """
    cell = np.floor(pt)
    f = (pt - cell).astype(np.float32)
    w_hi = f * f * (np.float32(3.0) - np.float32(2.0) * f)  # smoothstep weight of the upper corner, [3, N]
    w_lo = np.float32(1.0) - w_hi
    # Lattice coordinates as uint32 (negatives wrap; the hash is arithmetic mod 2^32 anyway), then
    # per-axis partial hashes of the two lattice coordinates each point touches.
    ic = cell.astype(np.int32).view(np.uint32)
    primes = np.array([0x8DA6B343, 0xD8163841, 0xCB1AB31F], dtype=np.uint32)[:, None]
    parts = (ic * primes, (ic + np.uint32(1)) * primes)
    salt32 = np.uint32(_mix32(np.array([salt & 0xFFFFFFFF], dtype=np.uint32))[0])
    out = np.zeros((channels, pt.shape[1]), dtype=np.float32)
    for dx in (0, 1):
        wx = (w_lo, w_hi)[dx][0]
        for dy in (0, 1):
            wxy = wx * (w_lo, w_hi)[dy][1]
            hxy = parts[dx][0] ^ parts[dy][1] ^ salt32
            for dz in (0, 1):
                wxyz = wxy * (w_lo, w_hi)[dz][2]
                h = _mix32(hxy ^ parts[dz][2])
                # Separate 10-bit fields of one hash give the channels' corner values.
                for c in range(channels):
                    out[c] += wxyz * ((h >> np.uint32(10 * c)) & np.uint32(1023)).astype(np.float32)
    out *= np.float32(1.0 / 1023.0)
    return out


def _rotation_from_seed(seed: int, k: int) -> np.ndarray:
    """A fixed pseudo-random rotation per (seed, octave), so lattice axes never align with walls."""
    q = np.random.default_rng([seed & 0xFFFFFFFF, k, 7]).normal(size=4)
    x, y, z, w = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def surface_texture(points_w: np.ndarray, seed: int = 0, strength: float = 1.0) -> np.ndarray:
    """Multiplicative RGB texture [N, 3] float32 at world points ``points_w`` [N, 3] (metres).

    Brightness is multi-octave value noise (periods from about 0.7 m down to about 3 cm) mapped to
    roughly 0.6-1.3, with low-frequency per-channel hue variation (up to about +-15 %) and darker blotches
    with sharp-ish edges. Deterministic in ``seed``; ``strength`` 0 gives all ones, 1 the full
    texture, and in between it blends linearly.
    """
    n = len(np.asarray(points_w).reshape(-1, 3))
    if strength == 0.0 or n == 0:
        return np.ones((n, 3), dtype=np.float32)
    # Work on [3, N] (contiguous per-axis rows); a (3, 3) @ (3, N) product per octave rotates and scales.
    pts = np.ascontiguousarray(np.asarray(points_w, dtype=np.float64).reshape(-1, 3).T)
    # Brightness: fractal sum of 5 octaves (lacunarity 2.13 so octaves never share a lattice).
    fbm = np.zeros(n, dtype=np.float32)
    total = 0.0
    freq, amp = 1.4, 1.0
    for k in range(5):
        fbm += np.float32(amp) * _value_noise((_rotation_from_seed(seed, k) * freq) @ pts, seed * 131 + k)[0]
        total += amp
        freq, amp = freq * 2.13, amp * 0.6
    fbm /= np.float32(total)
    # Value noise clusters around 0.5; stretch its contrast to use most of the 0.65-1.3 range.
    bright = np.float32(0.65) + np.float32(0.65) * np.clip(0.5 + 2.2 * (fbm - 0.5), 0.0, 1.0)
    # Blotches: thresholded mid-frequency noise (period 25 cm), 20 % darker, edges about 1 cm wide.
    blot = _value_noise((_rotation_from_seed(seed, 99) * 4.0) @ pts, seed * 131 + 99)[0]
    bright *= np.float32(1.0) - np.float32(0.2) * np.clip((blot - np.float32(0.62)) / np.float32(0.05), 0.0, 1.0)
    # Hue: low-frequency per-channel gain (period about 1 m), normalised to keep brightness.
    hue = np.float32(1.0) + np.float32(0.3) * (
        _value_noise(_rotation_from_seed(seed, 98) @ pts, seed * 131 + 98, channels=3) - np.float32(0.5)
    )
    tex = (bright[None, :] * (hue / hue.mean(axis=0, keepdims=True))).T
    if strength != 1.0:
        tex = np.float32(1.0) + np.float32(strength) * (tex - np.float32(1.0))
    return tex.astype(np.float32)


# --------------------------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------------------------


def camera_rays(T_wc: np.ndarray, intr: Intrinsics, pixel_offset: float = 0.0) -> np.ndarray:
    """Rays [H, W, 6] float32 (origin, direction) through pixel centres of a camera at ``T_wc`` [4, 4].

    Each direction is ``R_wc @ ((u + o - cx) / fx, (v + o - cy) / fy, 1)`` with ``o = pixel_offset``
    (0: integer pixel coordinates are pixel centres); its optical-axis component is 1, so a hit
    distance in ray-direction units is the z-depth in metres.
    """
    T = np.asarray(T_wc, dtype=np.float64)
    u = (np.arange(intr.width, dtype=np.float64) + pixel_offset - intr.cx) / intr.fx
    v = (np.arange(intr.height, dtype=np.float64) + pixel_offset - intr.cy) / intr.fy
    dirs_c = np.empty((intr.height, intr.width, 3), dtype=np.float64)
    dirs_c[..., 0] = u[None, :]
    dirs_c[..., 1] = v[:, None]
    dirs_c[..., 2] = 1.0
    rays = np.empty((intr.height, intr.width, 6), dtype=np.float32)
    rays[..., :3] = T[:3, 3]
    rays[..., 3:] = np.einsum("hwk,jk->hwj", dirs_c, T[:3, :3])
    return rays


class MeshRenderer:
    """Ray-casts one triangle mesh into RGB-D images at any pose; the BVH is built once and reused.

    ``texture_strength`` scales the procedural surface texture (0 disables it: plain vertex
    colours); ``texture_seed`` picks the texture pattern.
    """

    def __init__(self, mesh: o3d.geometry.TriangleMesh, texture_strength: float = 1.0, texture_seed: int = 0) -> None:
        if not np.isfinite(texture_strength) or texture_strength < 0:
            raise InputError("texture_strength", f"must be a finite number >= 0, got {texture_strength}")
        self.vertices = np.asarray(mesh.vertices, dtype=np.float64)  # [V, 3] metres
        self.triangles = np.asarray(mesh.triangles, dtype=np.int64)  # [F, 3]
        if len(self.triangles) == 0:
            raise InputError("mesh", "mesh has no triangles")
        if mesh.has_vertex_colors():
            self.colours = np.asarray(mesh.vertex_colors, dtype=np.float32)  # [V, 3] in [0, 1]
        else:
            self.colours = np.full((len(self.vertices), 3), _DEFAULT_GREY, dtype=np.float32)
        self.texture_strength = float(texture_strength)
        self.texture_seed = int(texture_seed)
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(
            o3d.core.Tensor(self.vertices.astype(np.float32)), o3d.core.Tensor(self.triangles.astype(np.uint32))
        )

    def _cast(
        self, T_wc: np.ndarray, intr: Intrinsics, pixel_offset: float
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Rays [H, W, 6] and open3d's raw hit record for a camera at ``T_wc``."""
        T = check_pose(T_wc, "T_wc")
        rays = camera_rays(T, intr, pixel_offset)
        hits = self._scene.cast_rays(o3d.core.Tensor(rays))
        keys = ("t_hit", "primitive_ids", "primitive_uvs", "primitive_normals")
        return rays, {k: hits[k].numpy() for k in keys}

    @staticmethod
    def _depth(t_hit: np.ndarray) -> np.ndarray:
        """z-depth [H, W] float32 metres from hit distances (directions have unit optical-axis component)."""
        return np.where(np.isfinite(t_hit), t_hit, 0.0).astype(np.float32)

    def render_depth(self, T_wc: np.ndarray, intr: Intrinsics, pixel_offset: float = 0.0) -> np.ndarray:
        """Depth only: [H, W] float32 z-depth in metres, 0 where the ray hits nothing.

        ``pixel_offset`` as in :func:`camera_rays` (:data:`REPLICA_PIXEL_OFFSET` mimics Replica).
        """
        _, hits = self._cast(T_wc, intr, pixel_offset)
        return self._depth(hits["t_hit"])

    def render(self, T_wc: np.ndarray, intr: Intrinsics, pixel_offset: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Colour [H, W, 3] uint8 and z-depth [H, W] float32 metres (0, black where nothing is hit).

        ``pixel_offset`` as in :func:`camera_rays` (:data:`REPLICA_PIXEL_OFFSET` mimics Replica).
        """
        rays, hits = self._cast(T_wc, intr, pixel_offset)
        return self._shade(rays, hits, intr)

    def render_with_incidence(
        self, T_wc: np.ndarray, intr: Intrinsics, pixel_offset: float = 0.0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`render` and ``|cos|`` [H, W] float32 of the angle between each ray and the hit triangle's normal.

        The incidence (0 where nothing is hit) is what a sensor model needs for grazing-angle holes and
        angle-dependent noise (:mod:`roigsf_ros.data.sensor`); the absolute value makes it independent of
        the triangles' winding.
        """
        rays, hits = self._cast(T_wc, intr, pixel_offset)
        rgb, depth_m = self._shade(rays, hits, intr)
        dirs = rays[..., 3:].astype(np.float64)
        normals = hits["primitive_normals"].astype(np.float64)
        norm = np.linalg.norm(dirs, axis=-1) * np.linalg.norm(normals, axis=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            cos = np.abs(np.einsum("hwk,hwk->hw", dirs, normals)) / norm
        cos = np.where(np.isfinite(hits["t_hit"]) & (norm > 0), np.clip(cos, 0.0, 1.0), 0.0)
        return rgb, depth_m, cos.astype(np.float32)

    def _shade(self, rays: np.ndarray, hits: dict[str, np.ndarray], intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
        """Colour [H, W, 3] uint8 and depth [H, W] float32 of a cast (see :meth:`render`)."""
        t_hit = hits["t_hit"]
        depth_m = self._depth(t_hit)
        hit = np.isfinite(t_hit)
        rgb = np.zeros((intr.height, intr.width, 3), dtype=np.uint8)
        if not hit.any():
            return rgb, depth_m
        prim = hits["primitive_ids"][hit].astype(np.int64)
        uv = hits["primitive_uvs"][hit]  # barycentric: p = (1-u-v) v0 + u v1 + v v2
        tri = self.triangles[prim]  # [M, 3]
        bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1).astype(np.float32)
        colour = np.einsum("mk,mkc->mc", bary, self.colours[tri])  # [M, 3]
        if self.texture_strength > 0:
            r = rays[hit].astype(np.float64)
            points_w = r[:, :3] + r[:, 3:] * t_hit[hit].astype(np.float64)[:, None]
            colour = colour * surface_texture(points_w, self.texture_seed, self.texture_strength)
        rgb[hit] = np.clip(np.rint(colour * 255.0), 0, 255).astype(np.uint8)
        return rgb, depth_m


# --------------------------------------------------------------------------------------------
# Procedural room
# --------------------------------------------------------------------------------------------


def _quad_grid(origin: np.ndarray, u: np.ndarray, v: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertices [K, 3] and triangles [F, 3] of the rectangle ``origin + s u + t v``, cells about ``cell`` m.

    Triangles wind so that their normal is ``u x v``.
    """
    nu = max(1, round(np.linalg.norm(u) / cell))
    nv = max(1, round(np.linalg.norm(v) / cell))
    s, t = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1), indexing="ij")
    verts = origin[None, :] + s.reshape(-1, 1) * u[None, :] + t.reshape(-1, 1) * v[None, :]
    idx = np.arange((nu + 1) * (nv + 1)).reshape(nu + 1, nv + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    tris = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return verts, tris


class _MeshBuilder:
    """Accumulates vertices, triangles and vertex colours of several parts into one mesh."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.vertices: list[np.ndarray] = []
        self.triangles: list[np.ndarray] = []
        self.colours: list[np.ndarray] = []
        self.n = 0

    def add(self, vertices: np.ndarray, triangles: np.ndarray, colour: np.ndarray, jitter: float = 0.04) -> None:
        """Add a part with base ``colour`` [3]; vertex colours vary smoothly by about ``jitter``."""
        vertices = np.asarray(vertices, dtype=np.float64)
        # A smooth colour gradient across the part (plus tiny per-vertex variation) so that
        # interpolated vertex colour is not flat; seeded, so deterministic.
        g = self.rng.normal(scale=jitter, size=(3, 3))
        centred = vertices - vertices.mean(axis=0)
        span = max(float(np.abs(centred).max()), 1e-6)
        col = colour[None, :] + (centred / span) @ g + self.rng.normal(scale=jitter / 4, size=vertices.shape)
        self.vertices.append(vertices)
        self.triangles.append(np.asarray(triangles, dtype=np.int64) + self.n)
        self.colours.append(np.clip(col, 0.02, 0.98))
        self.n += len(vertices)

    def add_o3d(self, mesh: o3d.geometry.TriangleMesh, colour: np.ndarray, jitter: float = 0.04) -> None:
        """Add an open3d mesh part (its own colours ignored)."""
        self.add(np.asarray(mesh.vertices), np.asarray(mesh.triangles), colour, jitter)

    def grid(self, origin: np.ndarray, u: np.ndarray, v: np.ndarray, cell: float, colour: np.ndarray) -> None:
        """Add a rectangle ``origin + s u + t v`` (s, t in [0, 1]) of cells about ``cell`` metres; normal u x v."""
        self.add(*_quad_grid(origin, u, v, cell), colour, jitter=0.06)

    def box(self, lo: np.ndarray, hi: np.ndarray, colour: np.ndarray, cell: float = 0.15) -> None:
        """Add a closed axis-aligned box from ``lo`` to ``hi`` (outward normals), faces subdivided."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        ex, ey, ez = np.diag(hi - lo)
        for origin, u, v in (
            (lo, ey, ex),  # bottom, normal -z
            (lo + ez, ex, ey),  # top, normal +z
            (lo, ex, ez),  # normal -y
            (lo + ey, ez, ex),  # normal +y
            (lo, ez, ey),  # normal -x
            (lo + ex, ey, ez),  # normal +x
        ):
            self.add(*_quad_grid(origin, u, v, cell), colour, jitter=0.03)

    def cylinder(self, base: np.ndarray, radius: float, height: float, colour: np.ndarray, res: int = 24) -> None:
        """Add a closed vertical cylinder standing on ``base`` [3]."""
        m = o3d.geometry.TriangleMesh.create_cylinder(radius=radius, height=height, resolution=res, split=4)
        m.translate(np.asarray(base, float) + np.array([0.0, 0.0, height / 2]))
        self.add_o3d(m, colour, jitter=0.03)

    def sphere(self, centre: np.ndarray, radius: float, colour: np.ndarray, res: int = 16) -> None:
        """Add a UV sphere."""
        m = o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=res)
        m.translate(np.asarray(centre, float))
        self.add_o3d(m, colour, jitter=0.03)

    def bowl(self, centre: np.ndarray, radius: float, thickness: float, colour: np.ndarray, res: int = 24) -> None:
        """Add an open hemispherical bowl (outer and inner shell joined at the rim); ``centre`` is the rim centre."""
        theta = np.linspace(0.0, np.pi / 2, res // 2 + 1)  # polar angle from straight down to the rim
        phi = np.linspace(0.0, 2 * np.pi, res, endpoint=False)
        rings = []
        for r in (radius, radius - thickness):
            st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
            ring = np.stack([r * st * np.cos(phi), r * st * np.sin(phi), -r * ct * np.ones_like(phi)], -1)
            rings.append(ring)  # [T, P, 3]
        verts, tris = [], []
        nt, npf = len(theta), len(phi)
        for shell, ring in enumerate(rings):
            off = shell * nt * npf
            verts.append(ring.reshape(-1, 3))
            for i in range(nt - 1):
                for j in range(npf):
                    a, b = off + i * npf + j, off + i * npf + (j + 1) % npf
                    c, d = off + (i + 1) * npf + (j + 1) % npf, off + (i + 1) * npf + j
                    tris += [[a, b, c], [a, c, d]] if shell == 0 else [[a, c, b], [a, d, c]]
        top_o, top_i = (nt - 1) * npf, nt * npf + (nt - 1) * npf  # rim rings of the two shells
        for j in range(npf):
            a, b = top_o + j, top_o + (j + 1) % npf
            c, d = top_i + (j + 1) % npf, top_i + j
            tris += [[a, b, c], [a, c, d]]
        self.add(np.concatenate(verts) + np.asarray(centre, float), np.array(tris), colour, jitter=0.03)

    def mesh(self) -> o3d.geometry.TriangleMesh:
        """The accumulated mesh with vertex normals."""
        m = o3d.geometry.TriangleMesh()
        m.vertices = o3d.utility.Vector3dVector(np.concatenate(self.vertices))
        m.triangles = o3d.utility.Vector3iVector(np.concatenate(self.triangles).astype(np.int32))
        m.vertex_colors = o3d.utility.Vector3dVector(np.concatenate(self.colours))
        m.compute_vertex_normals()
        return m


def _palette(rng: np.random.Generator) -> np.ndarray:
    """A saturated-ish random colour [3] in [0, 1]."""
    hsv_h = rng.uniform(0, 1)
    s, v = rng.uniform(0.35, 0.8), rng.uniform(0.45, 0.9)
    k = (np.array([5.0, 3.0, 1.0]) + hsv_h * 6) % 6
    return v - v * s * np.clip(np.minimum(k, 4 - k), 0, 1)


def synth_room(seed: int) -> o3d.geometry.TriangleMesh:
    """A closed textured test room (:data:`ROOM_MIN` to :data:`ROOM_MAX`, z up) with seeded furniture.

    Walls, floor and ceiling face inward; contents: a table with thin legs (thin parts), an open
    shelf and a bowl (concavities), an L-shaped couch, a floor lamp (thin pole), a picture (thin
    plate on a wall), and seeded boxes, cylinders and spheres. Everything taller than 1.0 m stands
    within 0.6 m of a wall, so :func:`synth_trajectory` cameras never meet it. Vertex colours per
    object; deterministic for a ``seed``.
    """
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0x5EED])
    b = _MeshBuilder(rng)
    lo, hi = ROOM_MIN.astype(float), ROOM_MAX.astype(float)
    ex, ey, ez = np.diag(hi - lo)
    cell = 0.1
    wall_col = rng.uniform(0.6, 0.85, 3)
    b.grid(lo, ex, ey, cell, rng.uniform(0.35, 0.6, 3))  # floor, normal +z
    b.grid(lo + ez, ey, ex, cell, rng.uniform(0.75, 0.95, 3))  # ceiling, normal -z
    b.grid(lo, ez, ex, cell, wall_col)  # wall y = lo, normal +y
    b.grid(lo + ey, ex, ez, cell, wall_col * 0.95)  # wall y = hi, normal -y
    b.grid(lo, ey, ez, cell, wall_col * 0.9)  # wall x = lo, normal +x
    b.grid(lo + ex, ez, ey, cell, wall_col * 1.05)  # wall x = hi, normal -x

    # Table near the centre (under the camera loop's middle): thin top, four thin legs.
    tc = np.array([rng.uniform(-0.2, 0.2), rng.uniform(-0.15, 0.15), 0.0])
    tw, td, th = rng.uniform(1.0, 1.3), rng.uniform(0.6, 0.8), rng.uniform(0.72, 0.78)
    wood = _palette(rng)
    b.box(tc + np.array([-tw / 2, -td / 2, th - 0.03]), tc + np.array([tw / 2, td / 2, th]), wood, cell=0.1)
    for sx in (-1, 1):
        for sy in (-1, 1):
            leg = tc + np.array([sx * (tw / 2 - 0.06), sy * (td / 2 - 0.06), 0.0])
            b.cylinder(leg, 0.02, th - 0.03, wood * 0.8, res=12)
    # On the table: a bowl (concave) and a thin plate.
    b.bowl(tc + np.array([rng.uniform(-0.3, 0.0), rng.uniform(-0.15, 0.15), th + 0.12]), 0.12, 0.01, _palette(rng))
    plate_c = tc + np.array([rng.uniform(0.2, 0.4), rng.uniform(-0.15, 0.15), th])
    b.cylinder(plate_c, 0.11, 0.008, _palette(rng), res=32)

    # Open shelf against the +y wall (concave: back, sides, three shelves, open front).
    sx0 = rng.uniform(lo[0] + 0.3, lo[0] + 1.2)
    sw, sd, sh, t = rng.uniform(0.8, 1.2), 0.38, rng.uniform(1.5, 1.9), 0.02
    y1 = hi[1] - 0.01
    shelf_col = _palette(rng)
    b.box([sx0, y1 - t, 0.0], [sx0 + sw, y1, sh], shelf_col)  # back
    b.box([sx0, y1 - sd, 0.0], [sx0 + t, y1, sh], shelf_col)  # sides
    b.box([sx0 + sw - t, y1 - sd, 0.0], [sx0 + sw, y1, sh], shelf_col)
    for z in np.linspace(0.05, sh - t, 4):
        b.box([sx0 + t, y1 - sd, z], [sx0 + sw - t, y1, z + t], shelf_col)
    for k in range(3):  # a few items on the shelves
        cx = sx0 + rng.uniform(0.15, sw - 0.15)
        z0 = float(np.linspace(0.05, sh - t, 4)[k]) + t
        b.box([cx - 0.07, y1 - 0.3, z0], [cx + 0.07, y1 - 0.08, z0 + rng.uniform(0.1, 0.3)], _palette(rng))

    # L-shaped couch in the (-x, -y) corner: seat and backrest boxes, height < 0.9 m.
    couch = _palette(rng)
    cl = rng.uniform(1.4, 1.9)
    x0, y0 = lo[0] + 0.05, lo[1] + 0.05
    b.box([x0, y0, 0.0], [x0 + cl, y0 + 0.8, 0.42], couch)  # seat along the -y wall
    b.box([x0, y0, 0.42], [x0 + cl, y0 + 0.2, 0.85], couch * 0.9)  # backrest
    b.box([x0, y0 + 0.8, 0.0], [x0 + 0.8, y0 + 1.6, 0.42], couch)  # seat along the -x wall
    b.box([x0, y0 + 0.2, 0.42], [x0 + 0.2, y0 + 1.6, 0.85], couch * 0.9)

    # Floor lamp (thin pole) in the (+x, +y) corner and a picture (thin plate) on the +x wall.
    lamp = np.array([hi[0] - 0.3, hi[1] - 0.3, 0.0])
    b.cylinder(lamp, 0.15, 0.03, _palette(rng))
    b.cylinder(lamp, 0.012, 1.6, np.array([0.2, 0.2, 0.2]), res=10)
    b.sphere(lamp + np.array([0.0, 0.0, 1.7]), 0.14, np.array([0.95, 0.9, 0.7]))
    py = rng.uniform(lo[1] + 0.8, hi[1] - 1.6)
    b.box([hi[0] - 0.025, py, 1.1], [hi[0] - 0.005, py + 0.9, 1.8], _palette(rng), cell=0.1)

    # Seeded clutter in the free band between the camera loop and the (+x, -y) walls and around the table.
    spots = [
        np.array([hi[0] - 0.45, lo[1] + 0.45]),
        np.array([hi[0] - 0.45, 0.2]),
        np.array([0.9, lo[1] + 0.4]),
        np.array([0.6, hi[1] - 0.4]),
        np.array([lo[0] + 0.4, 0.9]),
    ]
    for k, xy in enumerate(spots):
        xy = xy + rng.uniform(-0.1, 0.1, 2)
        col = _palette(rng)
        kind = (k + int(rng.integers(0, 3))) % 3
        if kind == 0:
            w2 = rng.uniform(0.12, 0.3, 2)
            b.box([xy[0] - w2[0], xy[1] - w2[1], 0.0], [xy[0] + w2[0], xy[1] + w2[1], rng.uniform(0.2, 0.8)], col)
        elif kind == 1:
            b.cylinder([xy[0], xy[1], 0.0], rng.uniform(0.1, 0.25), rng.uniform(0.3, 0.9), col)
        else:
            r = rng.uniform(0.12, 0.3)
            b.sphere([xy[0], xy[1], r], r, col)
    return b.mesh()


SUITE_OFFSET_M = np.array([0.0, ROOM_MAX[1] - ROOM_MIN[1], 0.0])
"""Shift (m) of the suite's second room (:func:`synth_suite`): it stands beside the first, sharing the wall y = 2."""
SUITE_DOOR_M = (0.9, 2.1)
"""Width and height (m) of the doorway between the suite's two rooms."""


def _suite_rooms(seed: int) -> tuple[o3d.geometry.TriangleMesh, o3d.geometry.TriangleMesh]:
    """The suite's rooms: :func:`synth_room` of ``seed`` and of ``seed + 1`` moved by :data:`SUITE_OFFSET_M`."""
    return synth_room(seed), synth_room(seed + 1).translate(SUITE_OFFSET_M)


def _centroids(mesh: o3d.geometry.TriangleMesh) -> np.ndarray:
    """Triangle centroids [F, 3] (m) of ``mesh``."""
    return np.asarray(mesh.vertices)[np.asarray(mesh.triangles)].mean(axis=1)


SUITE_WALK_CLEAR_M = 0.9
"""Furniture above this height (m) must not stand in the doorway's passage: the walk goes through at 1.4 m."""


def _suite_furniture(seed: int) -> np.ndarray:
    """Centroids [F, 3] (m) of the suite's triangles that are not walls, floor or ceiling."""
    parts = []
    bounds = ((ROOM_MIN, ROOM_MAX), (ROOM_MIN + SUITE_OFFSET_M, ROOM_MAX + SUITE_OFFSET_M))
    for mesh, (lo, hi) in zip(_suite_rooms(seed), bounds, strict=True):
        c = _centroids(mesh)
        shell = (np.abs(c - lo) < 0.02).any(axis=1) | (np.abs(c - hi) < 0.02).any(axis=1)
        parts.append(c[~shell])
    return np.concatenate(parts)


def _suite_passage_counts(furniture: np.ndarray, left_m: float) -> tuple[int, int]:
    """Furniture triangles (above :data:`SUITE_WALK_CLEAR_M`, and in all) in the passage of a doorway whose left edge
    is at x = ``left_m``: the doorway plus 0.15 m either side, 1.2 m deep into both rooms, below the lintel.
    """
    width, height = SUITE_DOOR_M
    f = furniture
    inside = (f[:, 0] > left_m - 0.15) & (f[:, 0] < left_m + width + 0.15) & (np.abs(f[:, 1] - ROOM_MAX[1]) < 1.2)
    inside &= f[:, 2] < height
    return int(np.count_nonzero(inside & (f[:, 2] > SUITE_WALK_CLEAR_M))), int(np.count_nonzero(inside))


def suite_door_x(seed: int) -> float:
    """The x (m) of the doorway's centre in the wall y = 2 between the suite's rooms, for ``seed``.

    The doorway spans whole wall cells (0.1 m); of the positions from x = -2.0 to 1.1 (its left edge), the one whose
    passage holds the fewest furniture triangles above :data:`SUITE_WALK_CLEAR_M` (none for seeds 0-11, so the walk
    meets no furniture), then the fewest in all, then the nearest the centre (:func:`_suite_passage_counts`).
    """
    width = SUITE_DOOR_M[0]
    furniture = _suite_furniture(seed)
    lefts = np.round(np.arange(-2.0, 1.1 + 1e-9, 0.1), 6)
    keys = [(*_suite_passage_counts(furniture, float(left)), abs(left + width / 2)) for left in lefts]
    best = min(range(len(lefts)), key=lambda i: keys[i])
    return float(lefts[best] + width / 2)


def synth_suite(seed: int) -> o3d.geometry.TriangleMesh:
    """Two :func:`synth_room` rooms side by side (seeds ``seed`` and ``seed + 1``, the second at y = 2..6) joined by a
    doorway in their shared wall (:func:`suite_door_x`, :data:`SUITE_DOOR_M`): a stream scene where a trajectory
    meets a whole new room (:func:`suite_trajectory`), unlike one loop inside one room. Deterministic for a seed.
    """
    door_x = suite_door_x(seed)
    width, height = SUITE_DOOR_M
    wall_y = float(ROOM_MAX[1])
    out = o3d.geometry.TriangleMesh()
    for mesh in _suite_rooms(seed):
        c = _centroids(mesh)
        door = (np.abs(c[:, 1] - wall_y) < 0.02) & (np.abs(c[:, 0] - door_x) < width / 2) & (c[:, 2] < height)
        mesh.remove_triangles_by_mask(door)
        mesh.remove_unreferenced_vertices()
        out += mesh
    out.compute_vertex_normals()
    return out


# --------------------------------------------------------------------------------------------
# Trajectories
# --------------------------------------------------------------------------------------------


def _smooth_noise(
    rng: np.random.Generator, s: np.ndarray, amplitude: float, max_cycles: float = 3.5, n_waves: int = 4
) -> np.ndarray:
    """Sum of seeded sinusoids (0.5 to ``max_cycles`` cycles per sequence) of phase ``s`` [N]; |value| <= amplitude."""
    freqs = rng.uniform(0.5, max_cycles, n_waves)
    phases = rng.uniform(0, 2 * np.pi, n_waves)
    weights = rng.uniform(0.5, 1.0, n_waves)
    weights = weights / weights.sum()
    return amplitude * (weights[None, :] * np.sin(2 * np.pi * freqs[None, :] * s[:, None] + phases)).sum(1)


def look_at(position: np.ndarray, target: np.ndarray, up: np.ndarray, roll_rad: float = 0.0) -> np.ndarray:
    """Camera-to-world [4, 4] at ``position`` looking at ``target`` (OpenCV axes), image-up along ``up``."""
    z = np.asarray(target, float) - np.asarray(position, float)
    z /= np.linalg.norm(z)
    x = np.cross(-np.asarray(up, float), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=1)
    c, s = np.cos(roll_rad), np.sin(roll_rad)
    R = R @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = position
    return T


def synth_trajectory(
    seed: int,
    n_frames: int,
    room_min: np.ndarray = ROOM_MIN,
    room_max: np.ndarray = ROOM_MAX,
    height_range: tuple[float, float] = (1.25, 1.7),
    wall_margin: float = 0.5,
    loops: float = 1.0,
) -> np.ndarray:
    """Smooth handheld-like camera-to-world poses [N, 4, 4] float64 looping round the room centre.

    Position follows an ellipse 1 m inside the walls (``loops`` turns over the sequence) with
    smooth seeded wobble, at ``height_range`` metres; the look-at target sweeps along the walls on
    the far side and up and down over furniture height, with a few degrees of smooth roll. Positions
    stay at least ``wall_margin`` metres from every wall. World z is up (as in :func:`synth_room`).
    """
    if n_frames < 1:
        raise InputError("n_frames", f"must be >= 1, got {n_frames}")
    lo, hi = np.asarray(room_min, float), np.asarray(room_max, float)
    centre = (lo + hi) / 2
    half = (hi - lo) / 2
    if np.any(half[:2] <= wall_margin + 0.2) or height_range[1] > hi[2] - 0.2 or height_range[0] < lo[2] + 0.2:
        raise InputError("room bounds", f"room {lo.tolist()}..{hi.tolist()} is too small for the camera loop")
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0x7EA1])
    s = np.arange(n_frames) / max(n_frames, 1)  # sequence phase in [0, 1)
    theta = 2 * np.pi * loops * s + rng.uniform(0, 2 * np.pi)
    radii = np.maximum(half[:2] - max(1.0, wall_margin + 0.3), 0.2)
    wobble = 0.15
    pos = np.empty((n_frames, 3))
    pos[:, 0] = centre[0] + radii[0] * np.cos(theta) + _smooth_noise(rng, s, wobble)
    pos[:, 1] = centre[1] + radii[1] * np.sin(theta) + _smooth_noise(rng, s, wobble)
    h_mid, h_amp = np.mean(height_range), (height_range[1] - height_range[0]) / 2
    pos[:, 2] = h_mid + _smooth_noise(rng, s, h_amp)
    pos[:, :2] = np.clip(pos[:, :2], lo[:2] + wall_margin, hi[:2] - wall_margin)

    # Target on an ellipse near the walls, ahead of the camera by an angle that sweeps smoothly
    # between looking across the room (pi) and along the nearer walls (about pi/3 or 5pi/3).
    sweep = np.pi + _smooth_noise(rng, s, 0.45 * np.pi, max_cycles=2.0)
    tgt = np.empty((n_frames, 3))
    tgt[:, 0] = centre[0] + (half[0] - 0.3) * np.cos(theta + sweep)
    tgt[:, 1] = centre[1] + (half[1] - 0.3) * np.sin(theta + sweep)
    tgt[:, 2] = 0.9 + _smooth_noise(rng, s, 0.5)
    roll = _smooth_noise(rng, s, np.deg2rad(4.0))
    up = np.array([0.0, 0.0, 1.0])
    poses = np.stack([look_at(pos[i], tgt[i], up, roll[i]) for i in range(n_frames)])
    for i, T in enumerate(poses):
        check_pose(T, f"synth_trajectory pose {i}")
    return poses


def suite_trajectory(seed: int, n_frames: int) -> np.ndarray:
    """Camera-to-world poses [N, 4, 4] through :func:`synth_suite`: a loop in the first room (42 % of the frames),
    a walk through the doorway (16 %), a loop in the second room (the rest); each loop is :func:`synth_trajectory`
    of its room's seed. The walk turns smoothly (slerp) from the first loop's last view to the doorway's direction
    (+y, 15 deg down), goes 1 m either side of the wall at 1.4 m height, and turns to the second loop's first view.
    """
    if n_frames < 10:
        raise InputError("n_frames", f"the suite's walk needs >= 10 frames, got {n_frames}")
    from scipy.spatial.transform import Rotation, Slerp

    n_a, n_walk = round(0.42 * n_frames), round(0.16 * n_frames)
    first = synth_trajectory(seed, n_a)
    second = synth_trajectory(seed + 1, n_frames - n_a - n_walk, ROOM_MIN + SUITE_OFFSET_M, ROOM_MAX + SUITE_OFFSET_M)
    door_x, wall_y = suite_door_x(seed), float(ROOM_MAX[1])
    ahead = np.array([0.0, 1.0, -np.tan(np.radians(15.0))])
    door_R = look_at(np.zeros(3), ahead, np.array([0.0, 0.0, 1.0]))[:3, :3]
    knots = np.stack([first[-1][:3, 3], [door_x, wall_y - 1.0, 1.4], [door_x, wall_y + 1.0, 1.4], second[0][:3, 3]])
    seg = np.linalg.norm(np.diff(knots, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    turn_in = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([first[-1][:3, :3], door_R])))
    turn_out = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([door_R, second[0][:3, :3]])))
    walk = np.empty((n_walk, 4, 4))
    for i, d in enumerate(cum[-1] * (np.arange(n_walk) + 1) / (n_walk + 1)):
        k = min(int(np.searchsorted(cum, d, side="right")) - 1, 2)
        u = (d - cum[k]) / seg[k]
        T = np.eye(4)
        T[:3, 3] = knots[k] + u * (knots[k + 1] - knots[k])
        R = turn_in(u).as_matrix() if k == 0 else door_R if k == 1 else turn_out(u).as_matrix()
        T[:3, :3] = R
        walk[i] = T
    poses = np.concatenate([first, walk, second])
    for i, T in enumerate(poses):
        check_pose(T, f"suite_trajectory pose {i}")
    return poses


# --------------------------------------------------------------------------------------------
# Sequences
# --------------------------------------------------------------------------------------------


def render_sequence(
    mesh: o3d.geometry.TriangleMesh,
    poses: np.ndarray,
    intr: Intrinsics,
    out_dir: str | Path,
    texture_strength: float = 1.0,
    texture_seed: int = 0,
    pixel_offset: float = 0.0,
    overwrite: bool = False,
    jpeg_quality: int = 95,
    progress: bool = True,
    metadata: dict | None = None,
    sensor: SensorModel | None = None,
) -> Path:
    """Render ``poses`` [N, 4, 4] of ``mesh`` into a Replica-layout folder ``out_dir``, all or nothing.

    Writes ``results/frame*.jpg``, ``results/depth*.png``, ``traj.txt``, ``cam_params.json``, the
    ground-truth ``mesh.ply`` (same coordinates as the poses) and ``render.json`` (settings and
    ``metadata``), inside :func:`~roigsf_ros.core.fileio.atomic_dir`, so a failure leaves nothing under
    ``out_dir``. ``pixel_offset`` as in :func:`camera_rays` (0 keeps ``cam_params.json`` exact).
    With a ``sensor`` (:class:`~roigsf_ros.data.sensor.SensorModel`) every ideal frame goes through it
    (noisy depth with holes, noisy JPEG colour), ``traj.txt`` holds the poses as its tracker writes them
    (not exactly orthonormal, optionally drifting), ``traj_gt.txt`` the true ones, and ``render.json``
    the sensor's constants and hole fractions. ``progress``: a bar on stderr, as every library call draws it (the
    command line passes it on a terminal only). Returns ``out_dir``.
    """
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    if len(poses) == 0:
        raise InputError("poses", "no poses to render")
    for i, T in enumerate(poses):
        check_pose(T, f"pose {i}")
    renderer = MeshRenderer(mesh, texture_strength=texture_strength, texture_seed=texture_seed)
    out_dir = Path(out_dir)
    with atomic_dir(out_dir, overwrite, marks=SCENE_MARKS, what="a scene") as tmp:
        written = poses if sensor is None else sensor.poses(poses)

        def frames() -> Iterator[Frame]:
            for i, T in enumerate(tqdm(poses, desc=f"render {out_dir.name}", unit="frame", disable=not progress)):
                if sensor is None:
                    rgb, depth_m = renderer.render(T, intr, pixel_offset)
                    yield Frame(index=i, rgb=rgb, depth_m=depth_m, T_wc=T)
                    continue
                rgb, depth_m, cos_incidence = renderer.render_with_incidence(T, intr, pixel_offset)
                ideal = Frame(index=i, rgb=rgb, depth_m=depth_m, T_wc=written[i])
                yield sensor.frame(ideal, intr, cos_incidence)

        write_replica(tmp, intr, frames(), jpeg_quality=jpeg_quality)
        if sensor is not None:
            save_traj(tmp / "traj_gt.txt", poses)
        if not o3d.io.write_triangle_mesh(str(tmp / "mesh.ply"), mesh, write_ascii=False):
            raise OSError(f"{tmp / 'mesh.ply'}: open3d could not write the mesh")
        info = {
            "frames": len(poses),
            "width": intr.width,
            "height": intr.height,
            "texture_strength": float(texture_strength),
            "texture_seed": int(texture_seed),
            "pixel_offset": float(pixel_offset),
            "depth": "z-depth along the optical axis, metres = png / scale",
            **(metadata or {}),
        }
        if sensor is not None:
            dev = [orthonormality_error(T[:3, :3]) for T in written]
            info["sensor"] = sensor.describe() | {
                "traj": "traj.txt: the poses as the simulated tracker writes them; traj_gt.txt: the true poses",
                "pose_orthonormality_error": [min(dev), max(dev)],
                "pose_position_error_m_max": float(np.abs(written[:, :3, 3] - poses[:, :3, 3]).max()),
            }
        (tmp / "render.json").write_text(json.dumps(info, indent=2) + "\n")
    return out_dir


def synth_object(seed: int = 0) -> o3d.geometry.TriangleMesh:
    """An object-centric scene (not a room): a torus, sphere, cylinder, cone and box on a 0.8 m disc.

    Seed 0 is the fixed layout the NBV benchmark reports on; other seeds jitter each part's position by up
    to 5 cm and its colour slightly. Vertex colours only; the renderer adds the procedural texture.
    """
    rng = np.random.default_rng(seed)
    jitter = (lambda: np.zeros(3)) if seed == 0 else (lambda: np.append(rng.uniform(-0.05, 0.05, 2), 0.0))

    def part(
        mesh: o3d.geometry.TriangleMesh, colour: list[float], at: tuple[float, float, float]
    ) -> o3d.geometry.TriangleMesh:
        c = np.clip(np.asarray(colour) + (0 if seed == 0 else rng.uniform(-0.05, 0.05, 3)), 0, 1)
        mesh.translate(np.asarray(at) + jitter())
        mesh.paint_uniform_color(c)
        return mesh

    o3g = o3d.geometry.TriangleMesh
    torus = o3g.create_torus(0.22, 0.07, 64, 24).rotate(o3d.geometry.get_rotation_matrix_from_xyz((1.2, 0, 0)))
    box = o3g.create_box(0.3, 0.2, 0.18).rotate(o3d.geometry.get_rotation_matrix_from_xyz((0, 0, 0.5)))
    mesh = o3g.create_cylinder(0.8, 0.04, 96).translate((0, 0, -0.02)).paint_uniform_color([0.55, 0.45, 0.35])
    mesh += part(torus, [0.8, 0.3, 0.2], (0.25, 0.1, 0.3))
    mesh += part(o3g.create_sphere(0.16, 40), [0.2, 0.5, 0.8], (-0.3, 0.25, 0.16))
    mesh += part(o3g.create_cylinder(0.09, 0.5, 48), [0.3, 0.7, 0.3], (-0.15, -0.3, 0.25))
    mesh += part(o3g.create_cone(0.15, 0.35, 48), [0.85, 0.75, 0.2], (0.35, -0.35, 0.0))
    mesh += part(box, [0.6, 0.3, 0.7], (-0.45, -0.05, 0.0))
    mesh = mesh.subdivide_midpoint(2)
    mesh.compute_vertex_normals()
    return mesh


def _box(lo: tuple[float, ...], size: tuple[float, ...], colour: list[float] | np.ndarray) -> o3d.geometry.TriangleMesh:
    """An axis-aligned box with corner ``lo`` and edge lengths ``size`` (m), painted ``colour``."""
    return o3d.geometry.TriangleMesh.create_box(*size).translate(lo).paint_uniform_color(colour)


def _jittered_colour(rng: np.random.Generator, seed: int) -> Callable[[list[float]], np.ndarray]:
    """A colour as given for seed 0 (the fixed layouts), else moved by up to 0.05 per channel (draws from ``rng``)."""

    def colour(c: list[float]) -> np.ndarray:
        return np.clip(np.asarray(c) + (0 if seed == 0 else rng.uniform(-0.05, 0.05, 3)), 0, 1)

    return colour


def synth_clutter(seed: int = 0) -> o3d.geometry.TriangleMesh:
    """An object-centric scene with occlusion (not a room): a 3x3 block of tall boxes 8 cm apart and four open
    cabinets with 8 cm walls facing outward, on the 0.8 m disc of :func:`synth_object`.

    A cabinet's inside (24 cm wide, 27 cm deep and high) is seen only from in front of it, and its inner faces lie
    more than 5 cm from any outer face, so 20 views of a hemisphere do not reach everything within 5 cm (on
    :func:`synth_object` every policy's 5 cm recall saturates). Seed 0 is the fixed layout the NBV benchmark reports
    on; other seeds change each box's height by up to 5 cm and the colours slightly. Vertex colours only; the
    renderer adds the procedural texture.
    """
    rng = np.random.default_rng(seed)
    o3g = o3d.geometry.TriangleMesh
    colour, box = _jittered_colour(rng, seed), _box
    mesh = o3g.create_cylinder(0.8, 0.04, 96).translate((0, 0, -0.02)).paint_uniform_color([0.55, 0.45, 0.35])
    heights = (0.45, 0.30, 0.50, 0.35, 0.55, 0.30, 0.40, 0.50, 0.35)  # 0.14 m boxes at a 0.22 m pitch
    palette = ([0.8, 0.3, 0.2], [0.2, 0.5, 0.8], [0.3, 0.7, 0.3], [0.85, 0.75, 0.2], [0.6, 0.3, 0.7])
    for k, h in enumerate(heights):
        i, j = divmod(k, 3)
        h = h + (0 if seed == 0 else rng.uniform(-0.05, 0.05))
        mesh += box((-0.29 + 0.22 * i, -0.29 + 0.22 * j, 0.0), (0.14, 0.14, h), colour(palette[k % len(palette)]))
    # A cabinet opening towards +x (0.35 deep, 0.4 wide, 0.35 high, walls 0.08), turned to face each direction.
    parts = (
        ((0.40, -0.20, 0.0), (0.08, 0.40, 0.35)),  # back
        ((0.48, -0.20, 0.0), (0.27, 0.08, 0.35)),  # sides
        ((0.48, 0.12, 0.0), (0.27, 0.08, 0.35)),
        ((0.48, -0.12, 0.27), (0.27, 0.24, 0.08)),  # top
    )
    for turn, c in enumerate(([0.75, 0.6, 0.4], [0.4, 0.6, 0.75], [0.6, 0.75, 0.4], [0.75, 0.45, 0.6])):
        rot = o3d.geometry.get_rotation_matrix_from_xyz((0.0, 0.0, turn * np.pi / 2))
        for lo, size in parts:
            mesh += box(lo, size, colour(c)).rotate(rot, center=(0.0, 0.0, 0.0))
    mesh = mesh.subdivide_midpoint(2)
    mesh.compute_vertex_normals()
    return mesh


def orbit_trajectory(n_frames: int) -> np.ndarray:
    """[N, 4, 4] cameras orbiting :func:`synth_object` once at 0.9-1.4 m radius and 0.2-0.9 m height, looking at it."""
    poses = []
    for i in range(int(n_frames)):
        a = 2 * np.pi * i / n_frames
        r = 1.15 + 0.25 * np.sin(3 * a)
        h = 0.55 + 0.35 * np.sin(2 * a + 0.7)
        eye = np.array([r * np.cos(a), r * np.sin(a), h])
        target = np.array([0.1 * np.cos(5 * a), 0.1 * np.sin(5 * a), 0.15])
        poses.append(look_at(eye, target, np.array([0.0, 0.0, 1.0])))
    return np.stack(poses)


def synth_shelf(seed: int = 0) -> o3d.geometry.TriangleMesh:
    """A second object-centric scene with occlusion, for choosing the NBV options' constants (the benchmark reports
    on :func:`synth_clutter` and tunes nothing there): a shelf of 2x2 open compartments facing outward, a table with
    a crate under it, and an L of two walls whose inner corner faces outward, on the disc of :func:`synth_object`.

    Each part hides something from most of the hemisphere: the compartments' backs, the crate under the table top
    (seen only from low views on its side), the corner of the L. Seed 0 is the fixed layout; other seeds move each
    part by up to 3 cm and change the colours slightly. Vertex colours only.
    """
    rng = np.random.default_rng(seed)
    o3g = o3d.geometry.TriangleMesh

    colour, box = _jittered_colour(rng, seed), _box

    def jitter() -> np.ndarray:
        return np.zeros(3) if seed == 0 else np.append(rng.uniform(-0.03, 0.03, 2), 0.0)

    mesh = o3g.create_cylinder(0.8, 0.04, 96).translate((0, 0, -0.02)).paint_uniform_color([0.5, 0.5, 0.45])
    # The shelf: 0.52 wide, 0.28 deep, 0.52 high, 2x2 compartments open towards -y (boards 0.04 thick).
    shelf = o3g()
    c = colour([0.7, 0.5, 0.3])
    for lo, size in (
        ((-0.26, -0.30, 0.0), (0.52, 0.04, 0.52)),  # back
        ((-0.26, -0.58, 0.0), (0.04, 0.28, 0.52)),  # sides
        ((0.22, -0.58, 0.0), (0.04, 0.28, 0.52)),
        ((-0.02, -0.58, 0.0), (0.04, 0.28, 0.52)),  # middle
        ((-0.26, -0.58, 0.0), (0.52, 0.28, 0.04)),  # bottom, middle and top boards
        ((-0.26, -0.58, 0.24), (0.52, 0.28, 0.04)),
        ((-0.26, -0.58, 0.48), (0.52, 0.28, 0.04)),
    ):
        shelf += box(lo, size, c)
    mesh += shelf.translate(jitter())
    # The table (top 0.42 x 0.34 at 0.24-0.27 m on four legs) and a crate under it.
    table = box((0.18, -0.05, 0.24), (0.42, 0.34, 0.03), colour([0.3, 0.45, 0.7]))
    for x, y in ((0.18, -0.05), (0.57, -0.05), (0.18, 0.26), (0.57, 0.26)):
        table += box((x, y, 0.0), (0.03, 0.03, 0.24), colour([0.25, 0.25, 0.3]))
    table += box((0.30, 0.04, 0.0), (0.18, 0.16, 0.16), colour([0.8, 0.3, 0.25]))
    mesh += table.translate(jitter())
    # The L: two walls 0.45 long, 0.04 thick, 0.4 high, the inner corner facing (-x, +y).
    ell = box((-0.60, 0.15, 0.0), (0.45, 0.04, 0.40), colour([0.35, 0.65, 0.4]))
    ell += box((-0.19, 0.15, 0.0), (0.04, 0.45, 0.40), colour([0.35, 0.65, 0.4]))
    mesh += ell.translate(jitter())
    mesh = mesh.subdivide_midpoint(2)
    mesh.compute_vertex_normals()
    return mesh


def synth_bins(seed: int = 0) -> o3d.geometry.TriangleMesh:
    """A third object-centric scene with occlusion, made after the NBV options were fixed (issue 10's check on an
    object scene nothing was chosen on): two open-top bins, a tunnel open at both ends and a screen with a crate
    close behind it, on the disc of :func:`synth_object`.

    Unlike :func:`synth_clutter` (openings facing outward) and :func:`synth_shelf`, the bins open upward (their floors
    seen only from high views), the tunnel along x (its floor only from low views near its axis) and the crate's
    front only from views past the screen's edges. Seed 0 is the fixed layout; other seeds move each part by up to
    3 cm and change the colours slightly. Vertex colours only.
    """
    rng = np.random.default_rng(seed)
    o3g = o3d.geometry.TriangleMesh
    colour, box = _jittered_colour(rng, seed), _box

    def jitter() -> np.ndarray:
        return np.zeros(3) if seed == 0 else np.append(rng.uniform(-0.03, 0.03, 2), 0.0)

    def bin_(lo: tuple[float, float], size: tuple[float, float, float], c: list[float]) -> o3d.geometry.TriangleMesh:
        """An open-top bin: a floor board and four walls 0.03 thick, outer corner ``lo``, outer ``size``."""
        (x, y), (sx, sy, sz), t = lo, size, 0.03
        cc = colour(c)
        out = box((x, y, 0.0), (sx, sy, t), cc)
        for lo3, s3 in (
            ((x, y, t), (sx, t, sz - t)),
            ((x, y + sy - t, t), (sx, t, sz - t)),
            ((x, y + t, t), (t, sy - 2 * t, sz - t)),
            ((x + sx - t, y + t, t), (t, sy - 2 * t, sz - t)),
        ):
            out += box(lo3, s3, cc)
        return out

    mesh = o3g.create_cylinder(0.8, 0.04, 96).translate((0, 0, -0.02)).paint_uniform_color([0.45, 0.5, 0.55])
    mesh += bin_((0.15, 0.15), (0.30, 0.30, 0.26), [0.8, 0.35, 0.25]).translate(jitter())
    mesh += bin_((-0.50, 0.20), (0.22, 0.36, 0.20), [0.3, 0.55, 0.8]).translate(jitter())
    # The tunnel along x: 0.44 long, inside 0.18 wide and 0.14 high, walls and roof 0.03.
    tun = o3g()
    c = colour([0.4, 0.7, 0.35])
    for lo3, s3 in (
        ((-0.22, -0.24, 0.0), (0.44, 0.03, 0.14)),
        ((-0.22, -0.03, 0.0), (0.44, 0.03, 0.14)),
        ((-0.22, -0.24, 0.14), (0.44, 0.24, 0.03)),
    ):
        tun += box(lo3, s3, c)
    mesh += tun.translate(jitter())
    # The screen (0.46 wide, 0.04 thick, 0.45 high) facing -y, and a crate 0.06 behind it.
    scr = box((0.12, -0.62, 0.0), (0.46, 0.04, 0.45), colour([0.85, 0.8, 0.3]))
    scr += box((0.25, -0.52, 0.0), (0.20, 0.16, 0.22), colour([0.6, 0.35, 0.7]))
    mesh += scr.translate(jitter())
    mesh = mesh.subdivide_midpoint(2)
    mesh.compute_vertex_normals()
    return mesh


def synth_dining(seed: int = 0) -> o3d.geometry.TriangleMesh:
    """A fourth object-centric scene with occlusion, made in the fiftieth session after every NBV option was fixed
    (issue 10's held-out object scene): a table with two chairs pushed under it, a cabinet with its door half open, a
    plank leaning on the cabinet's back and a stool, on the disc of :func:`synth_object`.

    Unlike the earlier scenes, some of what it hides lies behind slanted surfaces: the cabinet's inside only past the
    door, turned 60 deg open, and the wedge under the leaning plank; the chairs' seats under the table top are seen by
    about a third of the hemisphere's views. Seed 0 is the fixed layout; other seeds move each part by up to 3 cm and
    change the colours slightly. Vertex colours only.
    """
    rng = np.random.default_rng(seed)
    o3g = o3d.geometry.TriangleMesh
    colour, box = _jittered_colour(rng, seed), _box

    def jitter() -> np.ndarray:
        return np.zeros(3) if seed == 0 else np.append(rng.uniform(-0.03, 0.03, 2), 0.0)

    def turned(
        part: o3d.geometry.TriangleMesh, xyz_rad: tuple[float, float, float], centre: tuple[float, float, float]
    ) -> o3d.geometry.TriangleMesh:
        """``part`` turned in place by the x-y-z Euler angles ``xyz_rad`` about ``centre`` (m)."""
        return part.rotate(o3d.geometry.get_rotation_matrix_from_xyz(xyz_rad), center=centre)

    def chair(c: np.ndarray) -> o3d.geometry.TriangleMesh:
        """A chair facing +x: seat 0.20 x 0.20 at 0.20-0.23 m on four legs, its back along x = 0 up to 0.47 m."""
        out = box((0.0, 0.0, 0.20), (0.20, 0.20, 0.03), c)
        for x, y in ((0.0, 0.0), (0.175, 0.0), (0.0, 0.175), (0.175, 0.175)):
            out += box((x, y, 0.0), (0.025, 0.025, 0.20), c)
        return out + box((0.0, 0.0, 0.23), (0.03, 0.20, 0.24), c)

    mesh = o3g.create_cylinder(0.8, 0.04, 96).translate((0, 0, -0.02)).paint_uniform_color([0.5, 0.45, 0.5])
    # The table: top 0.46 x 0.36 at 0.40-0.43 m over (0.02..0.48, -0.03..0.33), legs 0.03 square.
    table = box((0.02, -0.03, 0.40), (0.46, 0.36, 0.03), colour([0.55, 0.35, 0.2]))
    for x, y in ((0.03, -0.02), (0.44, -0.02), (0.03, 0.29), (0.44, 0.29)):
        table += box((x, y, 0.0), (0.03, 0.03, 0.40), colour([0.3, 0.2, 0.15]))
    # Two chairs pushed in: one from -x (its seat 0.10 under the top), one from +y turned to face -y.
    table += chair(colour([0.25, 0.5, 0.75])).translate((-0.08, 0.05, 0.0))
    table += turned(chair(colour([0.75, 0.55, 0.25])), (0.0, 0.0, -np.pi / 2), (0.0, 0.0, 0.0)).translate(
        (0.15, 0.45, 0.0)
    )
    mesh += table.translate(jitter())
    # The cabinet: 0.32 wide (x), 0.29 deep, 0.46 high, walls 0.03, open towards -y, with a middle board; its door
    # (0.32 x 0.02 x 0.46) hinged at the opening's +x edge and turned 60 deg open, outward.
    cab = o3g()
    c = colour([0.35, 0.6, 0.45])
    for lo3, s3 in (
        ((-0.58, -0.10, 0.0), (0.32, 0.03, 0.46)),  # back
        ((-0.58, -0.36, 0.0), (0.03, 0.26, 0.46)),  # sides
        ((-0.29, -0.36, 0.0), (0.03, 0.26, 0.46)),
        ((-0.58, -0.36, 0.0), (0.32, 0.26, 0.03)),  # bottom, middle board, top
        ((-0.58, -0.36, 0.22), (0.32, 0.26, 0.02)),
        ((-0.58, -0.36, 0.43), (0.32, 0.26, 0.03)),
    ):
        cab += box(lo3, s3, c)
    door = box((-0.58, -0.38, 0.0), (0.32, 0.02, 0.46), colour([0.8, 0.8, 0.7]))
    cab += turned(door, (0.0, 0.0, np.pi / 3), (-0.26, -0.37, 0.0))
    # The plank (0.16 x 0.02 x 0.45) leaning on the cabinet's back, 20 deg from upright: its top touches the back
    # (0.342: sin 20 deg, rounded, as the fiftieth session's benches ran it).
    plank = box((-0.08, 0.0, 0.0), (0.16, 0.02, 0.45), colour([0.85, 0.7, 0.3]))
    cab += turned(plank, (np.radians(20.0), 0.0, 0.0), (0.0, 0.0, 0.0)).translate((-0.42, -0.07 + 0.45 * 0.342, 0.0))
    mesh += cab.translate(jitter())
    # A stool in the open: a cylinder 0.12 m in radius, 0.30 high.
    stool = (
        o3g.create_cylinder(0.12, 0.30, 32).translate((0.35, -0.45, 0.15)).paint_uniform_color(colour([0.7, 0.3, 0.35]))
    )
    mesh += stool.translate(jitter())
    mesh = mesh.subdivide_midpoint(2)
    mesh.compute_vertex_normals()
    return mesh


def dome_trajectory(n_frames: int) -> np.ndarray:
    """[N, 4, 4] cameras on a hemisphere over :func:`synth_object`, looking at it: 10-75 deg elevation, 1.0-1.3 m.

    Golden-angle azimuths with the elevation rising along the sequence (equal area per view), so the views see
    the parts' tops, sides and the gaps between them (one orbit at one height leaves little to choose).
    """
    golden = np.pi * (3.0 - np.sqrt(5.0))
    lo, hi = np.sin(np.radians(10.0)), np.sin(np.radians(75.0))
    poses = []
    for i in range(int(n_frames)):
        u = (i + 0.5) / n_frames
        elev = np.arcsin(lo + (hi - lo) * u)
        a = golden * i
        r = 1.0 + 0.3 * ((i * 0.618034) % 1.0)
        eye = np.array([r * np.cos(elev) * np.cos(a), r * np.cos(elev) * np.sin(a), 0.1 + r * np.sin(elev)])
        target = np.array([0.15 * np.cos(3 * a), 0.15 * np.sin(3 * a), 0.15])
        poses.append(look_at(eye, target, np.array([0.0, 0.0, 1.0])))
    return np.stack(poses)


__all__ = [
    "REPLICA_PIXEL_OFFSET",
    "ROOM_MAX",
    "ROOM_MIN",
    "SUITE_DOOR_M",
    "SUITE_OFFSET_M",
    "SUITE_WALK_CLEAR_M",
    "MeshRenderer",
    "camera_rays",
    "dome_trajectory",
    "load_mesh",
    "look_at",
    "orbit_trajectory",
    "render_sequence",
    "suite_door_x",
    "suite_trajectory",
    "surface_texture",
    "synth_bins",
    "synth_clutter",
    "synth_dining",
    "synth_object",
    "synth_room",
    "synth_shelf",
    "synth_suite",
    "synth_trajectory",
]
