"""2D Gaussian surfels (2DGS parameterisation) as a bundle of torch tensors, PLY I/O, RGB-D seeding.

Raw (optimised) parameters are stored; activated values come from the accessors: ``scales() =
exp(log_scales)`` in metres, ``opacities() = sigmoid(opacity_logits)``, ``rotations()`` from the
normalised (w, x, y, z) quaternions with columns ``t_u, t_v`` (tangents) and ``t_w = t_u x t_v``
(the surfel normal), and colour ``0.5 + C0 * sh_dc (+ degree-1 SH terms)`` as in 2DGS/3DGS.
The PLY layout is the one hbb1/2d-gaussian-splatting writes, so other 2DGS tools open the files.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from roigsf_ros.core.camera import Intrinsics, check_pose
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.fileio import atomic_path
from roigsf_ros.core.frame import check_float_colour

SH_C0 = 0.28209479177387814
"""Zeroth-order real spherical-harmonic constant: colour = 0.5 + SH_C0 * sh_dc."""
SH_C1 = 0.4886025119029199
"""First-order real spherical-harmonic constant (2DGS/3DGS ``computeColorFromSH``)."""

PARAM_NAMES = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")
"""Names of the optimisable tensors of a SurfelMap, in a fixed order."""


def check_device(name: str, where: str) -> torch.device:
    """``name`` as a torch device this process can use ("cpu", "cuda", "cuda:N"), else InputError at ``where``.

    The surfels run on the CPU (numba kernels) or a CUDA device (the plain-torch renderer); a malformed name, another
    kind of device or a CUDA device this torch cannot see is refused here, not deep inside the first render.
    """
    try:
        device = torch.device(name)
    except (RuntimeError, TypeError):
        raise InputError(where, f"{name!r} is not a torch device (cpu, cuda, cuda:N)") from None
    if device.type not in ("cpu", "cuda"):
        raise InputError(where, f"{name!r}: only cpu and cuda[:N] are supported")
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise InputError(where, f"{name!r}: this torch ({torch.__version__}) sees no CUDA device")
        if (device.index or 0) >= torch.cuda.device_count():
            raise InputError(where, f"{name!r}: only {torch.cuda.device_count()} CUDA device(s) here")
    return device


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices [N, 3, 3] of (w, x, y, z) quaternions [N, 4] (normalised here first)."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    rows = (
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    )  # fmt: skip
    return torch.stack(rows, dim=-1).reshape(*quats.shape[:-1], 3, 3)


def rotmat_to_quat(R: Tensor) -> Tensor:
    """Unit (w, x, y, z) quaternions [N, 4], w >= 0, of rotation matrices [N, 3, 3] (Shepperd's method)."""
    m = R.reshape(-1, 3, 3)
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = m.reshape(-1, 9).unbind(-1)
    tr = m00 + m11 + m22
    # Four candidate solutions, each well conditioned where its pivot is largest.
    cands = torch.stack(
        [
            torch.stack([1 + tr, m21 - m12, m02 - m20, m10 - m01], -1),
            torch.stack([m21 - m12, 1 + m00 - m11 - m22, m01 + m10, m02 + m20], -1),
            torch.stack([m02 - m20, m01 + m10, 1 + m11 - m00 - m22, m12 + m21], -1),
            torch.stack([m10 - m01, m02 + m20, m12 + m21, 1 + m22 - m00 - m11], -1),
        ],
        dim=1,
    )  # [N, 4, 4]
    pivot = torch.stack([tr, m00, m11, m22], -1).argmax(-1)
    q = cands.gather(1, pivot[:, None, None].expand(-1, 1, 4)).squeeze(1)
    q = q / q.norm(dim=-1, keepdim=True)
    q = torch.where(q[:, :1] < 0, -q, q)
    return q.reshape(*R.shape[:-2], 4)


def sh_to_color(sh_dc: Tensor, sh_rest: Tensor | None = None, viewdirs: Tensor | None = None) -> Tensor:
    """Colour [N, 3] (clamped >= 0, as 2DGS) of SH coefficients; ``viewdirs`` [N, 3] camera->surfel.

    ``sh_rest`` [N, 3, 3] holds the degree-1 coefficients (coefficient, channel); it is used only when
    ``viewdirs`` is given (directions are normalised here).
    """
    color = 0.5 + SH_C0 * sh_dc
    if sh_rest is not None and viewdirs is not None:
        d = viewdirs / viewdirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        x, y, z = d.unbind(-1)
        c1, c2, c3 = sh_rest.unbind(1)
        color = color - SH_C1 * y[:, None] * c1 + SH_C1 * z[:, None] * c2 - SH_C1 * x[:, None] * c3
    return color.clamp_min(0.0)


@dataclass
class SurfelMap:
    """N 2D Gaussian surfels; raw parameters, world frame, metres.

    ``means`` [N, 3]; ``quats`` [N, 4] (w, x, y, z), normalised on use; ``log_scales`` [N, 2]
    (s_u, s_v); ``opacity_logits`` [N]; ``sh_dc`` [N, 3]; optional ``sh_rest`` [N, 3, 3]
    (degree-1 SH, indexed [surfel, coefficient, channel] as 2DGS's ``_features_rest``).
    """

    means: Tensor
    quats: Tensor
    log_scales: Tensor
    opacity_logits: Tensor
    sh_dc: Tensor
    sh_rest: Tensor | None = None

    def __post_init__(self) -> None:
        n = self.means.shape[0] if self.means.dim() == 2 else -1
        expected = {
            "means": (n, 3),
            "quats": (n, 4),
            "log_scales": (n, 2),
            "opacity_logits": (n,),
            "sh_dc": (n, 3),
            "sh_rest": (n, 3, 3),
        }
        for name, shape in expected.items():
            t = getattr(self, name)
            if t is None:
                continue
            if not isinstance(t, Tensor):
                raise InputError("SurfelMap", f"{name} must be a torch.Tensor, got {type(t).__name__}")
            if n < 0 or tuple(t.shape) != shape:
                raise InputError("SurfelMap", f"{name} must have shape {list(shape)}, got {list(t.shape)}")
            if t.device != self.means.device or not t.is_floating_point():
                raise InputError("SurfelMap", f"{name} must be a floating tensor on {self.means.device}")

    # ----------------------------------------------------------------------------- construction
    @classmethod
    def empty(
        cls, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32, sh_degree: int = 0
    ) -> SurfelMap:
        """A map with no surfels (``sh_degree`` 1 gives an empty ``sh_rest``)."""
        z = lambda *s: torch.zeros(*s, device=device, dtype=dtype)  # noqa: E731
        return cls(z(0, 3), z(0, 4), z(0, 2), z(0), z(0, 3), z(0, 3, 3) if sh_degree >= 1 else None)

    @classmethod
    def cat(cls, maps: Sequence[SurfelMap]) -> SurfelMap:
        """Concatenate maps; a missing ``sh_rest`` counts as zeros when any map has one."""
        if not maps:
            raise InputError("SurfelMap.cat", "needs at least one map")
        any_rest = any(m.sh_rest is not None for m in maps)
        kw = {}
        for name in PARAM_NAMES:
            if name == "sh_rest":
                kw[name] = torch.cat([m._rest_or_zeros() for m in maps]) if any_rest else None
            else:
                kw[name] = torch.cat([getattr(m, name) for m in maps])
        return cls(**kw)

    def append(self, other: SurfelMap) -> SurfelMap:
        """A new map with ``other``'s surfels after this map's."""
        return SurfelMap.cat([self, other])

    def _rest_or_zeros(self) -> Tensor:
        if self.sh_rest is not None:
            return self.sh_rest
        return self.sh_dc.new_zeros(len(self), 3, 3)

    def _map(self, fn) -> SurfelMap:  # noqa: ANN001 - a tensor -> tensor callable
        vals = {f.name: getattr(self, f.name) for f in fields(self)}
        return SurfelMap(**{k: (None if v is None else fn(v)) for k, v in vals.items()})

    def select(self, index: Tensor) -> SurfelMap:
        """The surfels picked by a bool mask [N] or an index tensor (a new map, no shared storage)."""
        if index.dtype == torch.bool and index.shape != (len(self),):
            raise InputError("SurfelMap.select", f"mask must have shape [{len(self)}], got {list(index.shape)}")
        index = index.to(self.means.device)
        if index.dtype == torch.bool:
            index = index.nonzero().squeeze(1)
        return self._map(lambda t: t.index_select(0, index))

    def prune(self, remove: Tensor) -> SurfelMap:
        """The map without the surfels where the bool mask ``remove`` [N] is true."""
        return self.select(~remove.to(torch.bool))

    def clone(self) -> SurfelMap:
        """A deep copy (autograd history kept, as ``Tensor.clone``)."""
        return self._map(lambda t: t.clone())

    def detach(self) -> SurfelMap:
        """The same values cut from autograd (shared storage)."""
        return self._map(lambda t: t.detach())

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> SurfelMap:
        """A copy on ``device`` and/or in floating ``dtype``."""
        return self._map(lambda t: t.to(device=device, dtype=dtype))

    def requires_grad_(self, requires_grad: bool = True) -> SurfelMap:
        """Mark every parameter tensor (in place) as an autograd leaf that needs gradients; returns self."""
        for t in self.parameters():
            t.requires_grad_(requires_grad)
        return self

    def named_parameters(self) -> dict[str, Tensor]:
        """Parameter tensors by name (``sh_rest`` only when present), for optimiser groups."""
        return {n: getattr(self, n) for n in PARAM_NAMES if getattr(self, n) is not None}

    def parameters(self) -> list[Tensor]:
        """Parameter tensors in ``PARAM_NAMES`` order."""
        return list(self.named_parameters().values())

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def device(self) -> torch.device:
        """Device of the tensors."""
        return self.means.device

    @property
    def dtype(self) -> torch.dtype:
        """Floating dtype of the tensors."""
        return self.means.dtype

    @property
    def sh_degree(self) -> int:
        """0 without ``sh_rest``, 1 with."""
        return 0 if self.sh_rest is None else 1

    # ------------------------------------------------------------------------------ activations
    def scales(self) -> Tensor:
        """Standard deviations (s_u, s_v) [N, 2] in metres."""
        return torch.exp(self.log_scales)

    def opacities(self) -> Tensor:
        """Opacities [N] in (0, 1)."""
        return torch.sigmoid(self.opacity_logits)

    def rotations(self) -> Tensor:
        """Rotations [N, 3, 3]: columns t_u, t_v and the normal t_w = t_u x t_v (world frame)."""
        return quat_to_rotmat(self.quats)

    def normals(self) -> Tensor:
        """Unit surfel normals t_w [N, 3] (world frame; the sign is not oriented to any camera)."""
        return self.rotations()[..., 2]

    def colors(self, viewdirs: Tensor | None = None) -> Tensor:
        """RGB [N, 3] (>= 0); degree-1 SH is used when ``viewdirs`` [N, 3] (camera -> surfel) is given."""
        return sh_to_color(self.sh_dc, self.sh_rest, viewdirs)

    # -------------------------------------------------------------------------------------- PLY
    def save_ply(self, path: str | Path) -> None:
        """Write the 2DGS PLY (binary little-endian float32 vertices), atomically."""
        names = ply_field_names(self.sh_degree)
        n = len(self)
        d = self.detach().to(device="cpu", dtype=torch.float32)
        cols = [d.means.numpy(), np.zeros((n, 3), np.float32), d.sh_dc.numpy()]
        if d.sh_rest is not None:
            # 2DGS: features_rest [N, K, 3] -> transpose(1, 2).flatten -> channel-major f_rest_i.
            cols.append(d.sh_rest.transpose(1, 2).reshape(n, -1).numpy())
        cols += [d.opacity_logits.numpy()[:, None], d.log_scales.numpy(), d.quats.numpy()]
        data = np.ascontiguousarray(np.concatenate(cols, axis=1), dtype="<f4")
        header = "ply\nformat binary_little_endian 1.0\n" + f"element vertex {n}\n"
        header += "".join(f"property float {name}\n" for name in names) + "end_header\n"
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            fh.write(header.encode("ascii"))
            fh.write(data.tobytes())

    @classmethod
    def load_ply(
        cls, path: str | Path, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32
    ) -> SurfelMap:
        """Read a 2DGS PLY; SH above degree 1 is truncated to degree 1; errors name the file."""
        return _load_ply(Path(path), device, dtype)


def ply_field_names(sh_degree: int = 0) -> list[str]:
    """Vertex properties of a 2DGS PLY, in order (``sh_degree`` 0 or 1)."""
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * ((sh_degree + 1) ** 2 - 1))]
    return [*names, "opacity", "scale_0", "scale_1", "rot_0", "rot_1", "rot_2", "rot_3"]


_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


def _load_ply(path: Path, device: torch.device | str | None, dtype: torch.dtype) -> SurfelMap:
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise InputError(path, "PLY file not found") from None
    except OSError as exc:
        raise InputError(path, f"cannot read PLY file: {exc}") from None
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply\n") or end < 0:
        raise InputError(path, "not a PLY file (missing 'ply' magic or 'end_header')")
    lines = raw[:end].decode("ascii", errors="replace").splitlines()[1:]
    body = raw[end + len(b"end_header\n") :]
    fmt, n_vertex, props, elements = None, None, [], []
    for line in lines:
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format":
            fmt = tok[1:]
        elif tok[0] == "element" and len(tok) == 3:
            elements.append(tok[1])
            if tok[1] == "vertex":
                n_vertex = int(tok[2]) if tok[2].isdigit() else None
        elif tok[0] == "property" and elements and elements[-1] == "vertex":
            if len(tok) != 3 or tok[1] not in _PLY_TYPES:
                raise InputError(path, f"unsupported vertex property '{line.strip()}'")
            props.append((tok[2], "<" + _PLY_TYPES[tok[1]]))
    if fmt != ["binary_little_endian", "1.0"]:
        raise InputError(path, f"PLY format must be binary_little_endian 1.0, got {' '.join(fmt or ['none'])}")
    if elements[:1] != ["vertex"] or n_vertex is None:
        raise InputError(path, "PLY must start with a 'vertex' element with a vertex count")
    names = [p[0] for p in props]
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1"]
    required += ["rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [r for r in required if r not in names]
    if missing:
        raise InputError(path, f"not a 2DGS surfel PLY: missing vertex field(s) {', '.join(missing)}")
    if len(set(names)) != len(names):
        raise InputError(path, "duplicate vertex property names")
    rec = np.dtype(props)
    if len(body) < rec.itemsize * n_vertex:
        raise InputError(path, f"truncated: {n_vertex} vertices need {rec.itemsize * n_vertex} bytes, got {len(body)}")
    if elements == ["vertex"] and len(body) > rec.itemsize * n_vertex:  # the body is the vertices, nothing more
        raise InputError(
            path,
            f"{len(body) - rec.itemsize * n_vertex} bytes after the {n_vertex} vertices of {rec.itemsize} bytes "
            "(the header's count): a damaged or mis-written file",
        )
    v = np.frombuffer(body, dtype=rec, count=n_vertex)
    col = lambda *ns: np.stack([np.asarray(v[k], dtype=np.float64) for k in ns], axis=1)  # noqa: E731
    rest_names = sorted((k for k in names if re.fullmatch(r"f_rest_\d+", k)), key=lambda k: int(k[7:]))
    n_rest = len(rest_names)
    if n_rest % 3 or math.isqrt(n_rest // 3 + 1) ** 2 != n_rest // 3 + 1:
        raise InputError(path, f"{n_rest} f_rest fields is not 3 * ((degree + 1)^2 - 1) for any SH degree")
    if rest_names != [f"f_rest_{i}" for i in range(n_rest)]:
        raise InputError(path, "f_rest fields are not numbered 0..n-1")
    arrays = {
        "means": col("x", "y", "z"),
        "quats": col("rot_0", "rot_1", "rot_2", "rot_3"),
        "log_scales": col("scale_0", "scale_1"),
        "opacity_logits": col("opacity")[:, 0],
        "sh_dc": col("f_dc_0", "f_dc_1", "f_dc_2"),
    }
    if n_rest:
        k = n_rest // 3  # coefficients per channel, channel-major in the file
        rest = col(*rest_names).reshape(n_vertex, 3, k)[:, :, :3]  # keep degree 1
        arrays["sh_rest"] = np.ascontiguousarray(rest.transpose(0, 2, 1))
    for name, a in arrays.items():
        if not np.all(np.isfinite(a)):
            raise InputError(path, f"non-finite values in {name}")
    if n_vertex and np.any(np.linalg.norm(arrays["quats"], axis=1) == 0):
        raise InputError(path, "zero-length rotation quaternion")
    tensors = {k: torch.from_numpy(a).to(device=device, dtype=dtype) for k, a in arrays.items()}
    return SurfelMap(**tensors)


# ----------------------------------------------------------------------------------- RGB-D seeding
def _as_tensor(x: object, name: str, dtype: torch.dtype) -> Tensor:
    if isinstance(x, Tensor):
        return x.detach().to(device="cpu", dtype=dtype)
    try:
        return torch.as_tensor(np.asarray(x), dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise InputError(name, f"cannot convert to an array: {exc}") from None


def depth_to_points(depth_m: Tensor, intr: Intrinsics) -> Tensor:
    """Camera-frame points [H, W, 3] (OpenCV axes, metres) of a depth image [H, W] (pixel centre = index)."""
    h, w = depth_m.shape
    ys = torch.arange(h, dtype=depth_m.dtype, device=depth_m.device)[:, None]
    xs = torch.arange(w, dtype=depth_m.dtype, device=depth_m.device)[None, :]
    x = (xs - intr.cx) / intr.fx * depth_m
    y = (ys - intr.cy) / intr.fy * depth_m
    return torch.stack([x, y, depth_m], dim=-1)


def _tangent_diff(pts: Tensor, valid: Tensor, dim: int) -> tuple[Tensor, Tensor]:
    """One-sided difference along ``dim`` (forward or backward, whichever has the smaller depth jump)."""
    n = pts.shape[dim]
    nxt = torch.cat([pts.narrow(dim, 1, n - 1), pts.narrow(dim, n - 1, 1)], dim) - pts
    prv = pts - torch.cat([pts.narrow(dim, 0, 1), pts.narrow(dim, 0, n - 1)], dim)
    vn = torch.cat([valid.narrow(dim, 1, n - 1), torch.zeros_like(valid.narrow(dim, 0, 1))], dim) & valid
    vp = torch.cat([torch.zeros_like(valid.narrow(dim, 0, 1)), valid.narrow(dim, 0, n - 1)], dim) & valid
    use_next = vn & (~vp | (nxt[..., 2].abs() <= prv[..., 2].abs()))
    diff = torch.where(use_next[..., None], nxt, prv)
    return diff, vn | vp


def depth_normals(pts: Tensor, valid: Tensor) -> Tensor:
    """Unit normals [H, W, 3] of camera-frame points [H, W, 3], facing the camera (n . p < 0).

    Tangents are the one-sided neighbour differences with the smaller depth jump (so depth edges do
    not bend normals); pixels without a valid neighbour in both directions face the camera.
    """
    du, ok_u = _tangent_diff(pts, valid, 1)
    dv, ok_v = _tangent_diff(pts, valid, 0)
    n = torch.linalg.cross(du, dv, dim=-1)
    norm = n.norm(dim=-1, keepdim=True)
    ray = -pts / pts.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    ok = ok_u & ok_v & (norm[..., 0] > 1e-12)
    n = torch.where(ok[..., None], n / norm.clamp_min(1e-30), ray)
    flip = (n * pts).sum(-1, keepdim=True) > 0
    return torch.where(flip, -n, n)


def frame_from_normals(normals: Tensor, hint: Tensor) -> Tensor:
    """Rotations [N, 3, 3] with third column ``normals`` [N, 3] and first column ``hint`` ([3] or one per
    normal, [N, 3]) projected onto the tangent plane (another axis where the hint is nearly parallel to the normal).
    """
    n = normals / normals.norm(dim=-1, keepdim=True)
    h = hint.to(n).expand_as(n)
    alt = torch.tensor([0.0, 0.0, 1.0], dtype=n.dtype).expand_as(n)
    h = torch.where(((h * n).sum(-1, keepdim=True).abs() > 0.9), torch.linalg.cross(alt, h, dim=-1), h)
    tu = h - (h * n).sum(-1, keepdim=True) * n
    tu = tu / tu.norm(dim=-1, keepdim=True)
    tv = torch.linalg.cross(n, tu, dim=-1)
    return torch.stack([tu, tv, n], dim=-1)


def surfels_from_rgbd(
    rgb: Tensor | np.ndarray,
    depth_m: Tensor | np.ndarray,
    T_wc: np.ndarray | Tensor,
    intr: Intrinsics,
    mask: Tensor | np.ndarray | None = None,
    stride: int = 1,
    opacity: float = 0.7,
    scale_factor: float = 1.0,
    min_depth: float = 0.0,
    max_depth: float = math.inf,
    sh_degree: int = 0,
    max_stretch: float = 1.0,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> SurfelMap:
    """Surfels back-projected from an RGB-D frame: one per ``stride`` x ``stride`` pixel block.

    ``rgb`` [H, W, 3] in 0..1 (uint8 is divided by 255), ``depth_m`` [H, W] metres (NaN, <= min_depth
    or > max_depth skipped), ``T_wc`` [4, 4] camera-to-world, ``mask`` [H, W] bool keeps pixels.
    Normals come from the depth map (facing the camera); both scales are ``scale_factor * stride * depth / f``
    metres (the pixel footprint, isotropic as in SplaTAM and GauS-SLAM) when ``max_stretch`` is 1; above 1 the
    axis along the surface's tilt away from the camera is divided by the cosine of the incidence angle (at most
    ``max_stretch`` times longer), since a pixel's footprint on a tilted surface is that much longer along it and
    isotropic surfels leave gaps between them there. Every surfel gets ``opacity``.
    """
    T = check_pose(T_wc.detach().cpu().numpy() if isinstance(T_wc, Tensor) else T_wc, "T_wc")
    if stride < 1 or int(stride) != stride:
        raise InputError("stride", f"must be a positive integer, got {stride}")
    if not 0.0 < opacity < 1.0:
        raise InputError("opacity", f"must be in (0, 1), got {opacity}")
    if sh_degree not in (0, 1):
        raise InputError("sh_degree", f"must be 0 or 1, got {sh_degree}")
    if not max_stretch >= 1.0:
        raise InputError("max_stretch", f"must be at least 1, got {max_stretch}")
    h, w = intr.height, intr.width
    rgb_is_u8 = (isinstance(rgb, np.ndarray) and rgb.dtype == np.uint8) or (
        isinstance(rgb, Tensor) and rgb.dtype == torch.uint8
    )
    rgb_t = _as_tensor(rgb, "rgb", torch.float64) / (255.0 if rgb_is_u8 else 1.0)
    if not rgb_is_u8:
        check_float_colour(rgb_t.cpu().numpy(), "rgb")  # 0-255 as floats: refused, as Mapper.add_keyframe does
    depth = _as_tensor(depth_m, "depth", torch.float64)
    if tuple(rgb_t.shape) != (h, w, 3):
        raise InputError("rgb", f"expected shape [{h}, {w}, 3] (intrinsics {w}x{h}), got {list(rgb_t.shape)}")
    if tuple(depth.shape) != (h, w):
        raise InputError("depth", f"expected shape [{h}, {w}] (intrinsics {w}x{h}), got {list(depth.shape)}")
    valid = torch.isfinite(depth) & (depth > min_depth) & (depth <= max_depth)
    valid &= torch.isfinite(rgb_t).all(-1)
    if mask is not None:
        m = _as_tensor(mask, "mask", torch.float64)
        if tuple(m.shape) != (h, w):
            raise InputError("mask", f"expected shape [{h}, {w}], got {list(m.shape)}")
        valid &= m != 0
    depth = torch.where(valid, depth, torch.zeros_like(depth))
    pts = depth_to_points(depth, intr)
    normals = depth_normals(pts, valid)
    s = int(stride)
    sl = (slice(s // 2, None, s), slice(s // 2, None, s))
    keep = valid[sl]
    p_c = pts[sl][keep]
    n_c = normals[sl][keep]
    col = rgb_t[sl][keep].clamp(0.0, 1.0)
    R = torch.from_numpy(T[:3, :3])
    t = torch.from_numpy(T[:3, 3])
    means = p_c @ R.T + t
    f = math.sqrt(intr.fx * intr.fy)
    log_s = torch.log(p_c[:, 2] * (scale_factor * s / f))[:, None].expand(-1, 2)
    hint = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    if max_stretch > 1.0:
        # Tangent axis u along the tilt (the viewing ray's part in the surface plane), stretched by 1 / cos.
        ray = p_c / p_c.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        cos = (ray * n_c).sum(-1, keepdim=True)
        tilt = ray - cos * n_c
        frontal = tilt.norm(dim=-1, keepdim=True) < 1e-6  # any axis will do: the stretch there is 1
        hint = torch.where(frontal, hint, tilt)
        stretch = -torch.log(cos[:, 0].abs().clamp_min(1.0 / max_stretch))
        log_s = log_s + torch.stack([stretch, torch.zeros_like(stretch)], dim=-1)
    axes = frame_from_normals(n_c, hint)
    rot = R @ axes if len(p_c) else None
    quats = rotmat_to_quat(rot) if rot is not None else torch.zeros(0, 4, dtype=torch.float64)
    logit = math.log(opacity / (1.0 - opacity))
    out = SurfelMap(
        means=means,
        quats=quats,
        log_scales=log_s.contiguous(),
        opacity_logits=torch.full((len(p_c),), logit, dtype=torch.float64),
        sh_dc=(col - 0.5) / SH_C0,
        sh_rest=torch.zeros(len(p_c), 3, 3, dtype=torch.float64) if sh_degree else None,
    )
    return out.to(device=device, dtype=dtype)


__all__ = [
    "PARAM_NAMES",
    "SH_C0",
    "SH_C1",
    "SurfelMap",
    "check_device",
    "depth_normals",
    "depth_to_points",
    "frame_from_normals",
    "ply_field_names",
    "quat_to_rotmat",
    "rotmat_to_quat",
    "sh_to_color",
    "surfels_from_rgbd",
]
