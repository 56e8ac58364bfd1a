"""Sequences in the NICE-SLAM Replica layout, as NICE-SLAM, SplaTAM and MonoGS users have them.

Layout (``DIR`` is one scene, e.g. ``Replica/office0``)::

    DIR/results/frame000000.jpg   colour (also .png)
    DIR/results/depth000000.png   uint16 depth, metres = value / scale
    DIR/traj.txt                  one row-major 4x4 camera-to-world matrix per line (OpenCV axes)
    DIR/cam_params.json           {"camera": {w, h, fx, fy, cx, cy, scale}}; the Replica download
                                  keeps it in the parent folder, which is searched too

``DIR`` may also be the ``results`` folder itself. Frame ``N`` is paired with line ``N`` of
``traj.txt`` by the number in its file name.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterable, Iterator
from pathlib import Path

import cv2
import numpy as np

from roigsf_ros.core.camera import Intrinsics, load_pose, save_cam_params
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.frame import Frame, resize_frame
from roigsf_ros.data.sensor import load_camera

_LOG = logging.getLogger(__name__)

_FRAME_RE = re.compile(r"^frame(\d+)\.(jpg|jpeg|png)$", re.IGNORECASE)
MAX_DEPTH_M = 65535 / 6553.5
"""Largest depth a Replica uint16 PNG can hold at the standard scale (about 10 m)."""


SCENE_MARKS = ("cam_params.json", "traj.txt")
"""The files of a scene folder (this package's renders and NICE-SLAM's Replica): ``--overwrite`` replaces a folder
holding one of them, or an empty one, and no other."""


def load_traj(path: str | Path) -> np.ndarray:
    """Read ``traj.txt``: [N, 4, 4] float64 camera-to-world poses, each checked to be rigid, one a line (line k is
    frame k's: a blank line among them is refused, blank lines at the end are ignored).

    Rotations slightly off orthonormal (real-sensor trajectories) are re-orthonormalised with one
    warning for the file (:func:`roigsf_ros.core.camera.load_pose`).
    """
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except FileNotFoundError:
        raise InputError(path, "trajectory file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read trajectory: {exc}") from None
    while lines and not lines[-1].strip():  # blank lines at the end are only the end
        lines.pop()
    poses = []
    for lineno, line in enumerate(lines, start=1):
        if not line.strip():  # frame k pairs with pose line k: a skipped blank line would shift the later frames
            raise InputError(f"{path}:{lineno}", "blank line among the poses (line k is frame k's pose)")
        try:
            values = np.array([float(v) for v in line.split()], dtype=np.float64)
        except ValueError:
            raise InputError(f"{path}:{lineno}", "pose line has a value that is not a number") from None
        if values.size != 16:
            raise InputError(f"{path}:{lineno}", f"pose line has {values.size} values, expected 16")
        poses.append(load_pose(values.reshape(4, 4), f"{path}:{lineno}", source=str(path)))
    if not poses:
        raise InputError(path, "trajectory is empty")
    return np.stack(poses)


def save_traj(path: str | Path, poses: np.ndarray) -> None:
    """Write [N, 4, 4] poses as ``traj.txt`` (one row-major matrix per line, full precision)."""
    with open(path, "w") as f:
        for T in np.asarray(poses, dtype=np.float64).reshape(-1, 16):
            f.write(" ".join(f"{v:.18e}" for v in T) + "\n")


_JPEG_SOI, _JPEG_EOI = b"\xff\xd8\xff", b"\xff\xd9"
PNG_SIGNATURE, _PNG_IEND = b"\x89PNG\r\n\x1a\n", b"IEND\xaeB`\x82"
"""The first 8 bytes of every PNG file (and the last chunk's, whose absence means a truncated file)."""


def _read_image(path: str | Path, what: str) -> np.ndarray:
    """Decode an image file as stored (``IMREAD_UNCHANGED``); InputError naming the file if unreadable or cut short.

    OpenCV decodes a JPEG cut short without an error (the missing rows come out grey, with only a
    libjpeg warning on stderr), so JPEGs must end with the end-of-image marker FF D9 and PNGs with
    the IEND chunk.
    """
    try:
        data = Path(path).read_bytes()
    except FileNotFoundError:
        raise InputError(path, f"missing or unreadable {what}: file not found") from None
    except OSError as exc:
        raise InputError(path, f"missing or unreadable {what}: {exc.strerror or exc}") from None
    tail = data.rstrip(b"\0")  # some writers pad to a block size
    if data.startswith(_JPEG_SOI) and not tail.endswith(_JPEG_EOI):
        raise InputError(path, f"truncated {what}: no JPEG end-of-image marker (FF D9) in its {len(data)} bytes")
    if data.startswith(PNG_SIGNATURE) and not tail.endswith(_PNG_IEND):
        raise InputError(path, f"truncated {what}: no PNG IEND chunk at the end of its {len(data)} bytes")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
    if img is None:
        raise InputError(path, f"missing or unreadable {what}")
    return img


def read_rgb(path: str | Path) -> np.ndarray:
    """Colour image as [H, W, 3] uint8 RGB; InputError naming the file if unreadable or truncated."""
    img = _read_image(path, "colour image")
    if img.dtype != np.uint8:
        raise InputError(path, f"colour image must be 8-bit, got {img.dtype}")
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    elif img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_depth(path: str | Path, depth_scale: float) -> np.ndarray:
    """Depth PNG (uint16, metres = value / ``depth_scale``) as [H, W] float32 metres; InputError naming the file."""
    img = _read_image(path, "depth image")
    if img.dtype != np.uint16 or img.ndim != 2:
        raise InputError(path, f"depth image must be single-channel uint16, got {img.dtype} with shape {img.shape}")
    return img.astype(np.float32) / np.float32(depth_scale)


def find_cam_params(seq_dir: str | Path) -> Path | None:
    """``cam_params.json`` in the scene folder or its parent (the Replica download keeps it there)."""
    seq_dir = Path(seq_dir)
    for cand in (seq_dir / "cam_params.json", seq_dir.parent / "cam_params.json"):
        if cand.is_file():
            return cand
    return None


def _scenes_hint(root: Path, most: int = 5) -> str:
    """The error's hint naming the scene folders when ``root`` is a download holding some, else ""."""

    def is_scene(folder: Path) -> bool:
        try:
            return (folder / "results").is_dir() or any(_FRAME_RE.match(q.name) for q in folder.iterdir())
        except OSError:  # unreadable: not named
            return False

    scenes = sorted(p.name for p in root.iterdir() if p.is_dir() and is_scene(p))
    if not scenes:
        return ""
    named = ", ".join(scenes[:most]) + (f" and {len(scenes) - most} more" if len(scenes) > most else "")
    return f"; it holds scene folder(s) {named}: give one of them (e.g. {root / scenes[0]})"


class ReplicaSequence:
    """A Replica-layout sequence on disk, read lazily frame by frame.

    ``size`` resizes frames on load (:func:`resize_frame`: colour with area averaging, depth with
    pixel-centre-exact nearest neighbour so that no depth is invented across edges) and scales
    the intrinsics to match.
    ``allow_partial`` accepts a ``traj.txt`` with more poses than frames on disk (a partial
    download, like the 4-frame office0 sample); otherwise the counts must match.
    """

    def __init__(
        self,
        root: str | Path,
        cam: str | Path | Intrinsics | None = None,
        size: tuple[int | None, int | None] | None = None,
        allow_partial: bool = False,
    ) -> None:
        root = Path(root)
        if not root.is_dir():
            raise InputError(root, "is a file, not a scene folder" if root.exists() else "scene folder not found")
        if (root / "results").is_dir():
            self.root, self.results = root, root / "results"
        elif any(_FRAME_RE.match(p.name) for p in root.iterdir()):  # results/ itself, or a flat folder
            self.root = root if (root / "traj.txt").is_file() else root.parent
            self.results = root
        else:
            raise InputError(
                root, "no 'results/' folder with frameNNNNNN.jpg files (NICE-SLAM Replica layout)" + _scenes_hint(root)
            )

        if isinstance(cam, Intrinsics):
            native = cam
        else:
            cam_path = Path(cam) if cam is not None else find_cam_params(self.root)
            if cam_path is None:
                raise InputError(
                    self.root,
                    "no cam_params.json here or in the parent folder: put Replica's there, or give the camera "
                    "file (cam=PATH), or a named camera (cam=kinect-v1)",
                )
            native = load_camera(cam_path)  # a file, or a named camera (cam="kinect-v1")

        self.colour_paths: dict[int, Path] = {}
        for p in sorted(self.results.iterdir()):
            m = _FRAME_RE.match(p.name)
            if m:
                self.colour_paths[int(m.group(1))] = p
        if not self.colour_paths:
            raise InputError(self.results, "no frameNNNNNN.jpg colour images")
        self.indices = sorted(self.colour_paths)
        digits = len(_FRAME_RE.match(self.colour_paths[self.indices[0]].name).group(1))
        self.depth_paths = {i: self.results / f"depth{i:0{digits}d}.png" for i in self.indices}
        missing = [str(p) for p in self.depth_paths.values() if not p.is_file()]
        if missing:
            n = len(self.indices)
            raise InputError(missing[0], f"depth image missing ({len(missing)} of {n} frames have none)")

        traj_path = self.root / "traj.txt"
        all_poses = load_traj(traj_path)
        frames_dir = f"{self.results.name}/"  # results/, or a flat folder (which has no results/)
        if self.indices[-1] >= len(all_poses):
            raise InputError(
                traj_path,
                f"has {len(all_poses)} poses, too few: {frames_dir} holds frame number {self.indices[-1]} (line k "
                f"is frame k's pose: at least {self.indices[-1] + 1} lines needed)",
            )
        gaps = sorted(set(range(self.indices[-1])) - set(self.indices))  # frames missing between those on disk
        if gaps:  # a partial download stops early: a gap is a frame lost (or left out on purpose), named
            shown = ", ".join(f"frame{i:0{digits}d}.jpg" for i in gaps[:5]) + (" ..." if len(gaps) > 5 else "")
            why = f"{len(gaps)} frame(s) missing between frame 0 and frame {self.indices[-1]}: {shown}"
            if not allow_partial:
                raise InputError(self.results, f"{why} (frames left out on purpose need allow_partial=True)")
            _LOG.warning("%s: %s; read without them (a partial download, accepted)", self.results, why)
        if len(all_poses) != len(self.indices) and not allow_partial:
            raise InputError(
                traj_path,
                f"has {len(all_poses)} poses but {frames_dir} holds {len(self.indices)} frames "
                "(line count must match the frames; a partial download needs allow_partial=True)",
            )
        if len(all_poses) != len(self.indices):  # said, so that a run over 4 of 2000 frames does not pass unnoticed
            _LOG.warning("%s: %d frames on disk of the %d poses in traj.txt; reading those (a partial download, "
                         "accepted)", self.results, len(self.indices), len(all_poses))  # fmt: skip
        self.poses = all_poses[self.indices]
        self.native = native
        self.intrinsics = native.resized(*size) if size is not None else native
        self.traj_path = traj_path

    def __len__(self) -> int:
        return len(self.indices)

    def frame(self, k: int) -> Frame:
        """The ``k``-th frame on disk (its ``index`` is the number in its file name)."""
        i = self.indices[k]
        rgb = read_rgb(self.colour_paths[i])
        depth = read_depth(self.depth_paths[i], self.native.depth_scale)
        (dh, dw), (ch, cw) = depth.shape, rgb.shape[:2]  # the depth is checked first: it names its own file
        want = f"{self.native.width}x{self.native.height}"
        if (dw, dh) != (self.native.width, self.native.height):
            raise InputError(self.depth_paths[i], f"depth image is {dw}x{dh} but the camera parameters say {want}")
        if (cw, ch) != (self.native.width, self.native.height):
            raise InputError(self.colour_paths[i], f"colour image is {cw}x{ch} but the camera parameters say {want}")
        return resize_frame(Frame(index=i, rgb=rgb, depth_m=depth, T_wc=self.poses[k]), self.intrinsics)

    def __iter__(self) -> Iterator[Frame]:
        for k in range(len(self)):
            yield self.frame(k)


def write_replica(out_dir: str | Path, intr: Intrinsics, frames: Iterable[Frame], jpeg_quality: int = 95) -> int:
    """Write frames in the Replica layout under ``out_dir`` (renumbered from 0); return the count.

    Depth is stored as uint16 at ``intr.depth_scale``; non-finite or out-of-range depth becomes 0
    (invalid). Use :func:`roigsf_ros.core.fileio.atomic_dir` around it for an all-or-nothing folder.
    """
    out = Path(out_dir)
    (out / "results").mkdir(parents=True, exist_ok=True)
    poses = []
    for n, fr in enumerate(frames):
        if fr.rgb.shape[:2] != (intr.height, intr.width) or fr.depth_m.shape != (intr.height, intr.width):
            raise InputError(f"frame {fr.index}", f"image size does not match {intr.width}x{intr.height}")
        bgr = cv2.cvtColor(fr.rgb, cv2.COLOR_RGB2BGR)
        cv2.imwrite(str(out / "results" / f"frame{n:06d}.jpg"), bgr, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
        d = np.nan_to_num(fr.depth_m.astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0) * intr.depth_scale
        d = np.where((d > 0) & (d <= 65535), np.round(d), 0).astype(np.uint16)
        cv2.imwrite(str(out / "results" / f"depth{n:06d}.png"), d)
        poses.append(fr.T_wc)
    save_traj(out / "traj.txt", np.asarray(poses).reshape(-1, 4, 4))
    save_cam_params(out / "cam_params.json", intr)
    return len(poses)


def scene_gt_mesh(folder: Path) -> Path | None:
    """The ground-truth mesh of a scene or bag folder (a bag's ``.mcap`` file stands for its folder): ``mesh.ply`` in it
    (``roigsf scene`` folders, bags from ``roigsf bag from-replica``), else ``NAME_mesh.ply`` beside the folder ``NAME``
    (NICE-SLAM's Replica layout, ``Replica/office0_mesh.ply`` beside ``Replica/office0``, and the shipped sample bag's).
    None when neither is there: nothing is scored against a mesh that was not put with it.
    """
    folder = folder if folder.is_dir() else folder.parent
    for mesh in (folder / "mesh.ply", folder.parent / f"{folder.name}_mesh.ply"):
        if mesh.is_file():
            return mesh
    return None


__all__ = [
    "MAX_DEPTH_M",
    "SCENE_MARKS",
    "ReplicaSequence",
    "find_cam_params",
    "load_traj",
    "read_depth",
    "read_rgb",
    "save_traj",
    "scene_gt_mesh",
    "write_replica",
]
