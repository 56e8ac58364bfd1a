"""One way to read posed RGB-D frames for the mapper: a rosbag2 bag or a Replica-layout folder.

:func:`open_frames` returns a :class:`FrameSource` with the (possibly resized) intrinsics, a frame
count and re-iterable frames as :class:`roigsf_ros.data.replica.Frame`. Scene folders written by
``roigsf scene render/synth`` also carry the ground-truth ``mesh.ply``, exposed as ``gt_mesh_path``.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Protocol

import numpy as np

from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.frame import Frame, resize_frame
from roigsf_ros.data.bags import BagReader, CameraTopics
from roigsf_ros.data.replica import ReplicaSequence


class FrameSequence(Protocol):
    """What the mapper's offline loop needs: intrinsics, a frame count and re-iterable frames."""

    intrinsics: Intrinsics

    def __len__(self) -> int: ...

    def __iter__(self) -> Iterator[Frame]: ...


class FrameSource:
    """Posed RGB-D frames from disk, re-iterable; ``len`` is the number of frames after stride and cap."""

    kind = "base"

    def __init__(self, path: Path, intrinsics: Intrinsics, n_frames: int, gt_mesh_path: Path | None) -> None:
        self.path = path
        self.intrinsics = intrinsics
        self.n_frames = n_frames
        self.gt_mesh_path = gt_mesh_path

    def __len__(self) -> int:
        return self.n_frames

    def __iter__(self) -> Iterator[Frame]:
        raise NotImplementedError

    def poses(self) -> np.ndarray:
        """All frame poses [N, 4, 4] (float64 camera-to-world), in iteration order."""
        return np.stack([f.T_wc for f in self]) if self.n_frames else np.zeros((0, 4, 4))


class ReplicaFrameSource(FrameSource):
    """Frames of a Replica-layout folder (see :mod:`roigsf_ros.data.replica`)."""

    kind = "replica"

    def __init__(
        self,
        path: Path,
        size: tuple[int | None, int | None] | None,
        stride: int,
        max_frames: int | None,
        allow_partial: bool,
    ) -> None:
        self.seq = ReplicaSequence(path, size=size, allow_partial=allow_partial)
        self.ks = list(range(0, len(self.seq), stride))[: max_frames if max_frames is not None else None]
        mesh = self.seq.root / "mesh.ply"
        super().__init__(Path(path), self.seq.intrinsics, len(self.ks), mesh if mesh.is_file() else None)

    def __iter__(self) -> Iterator[Frame]:
        for k in self.ks:
            yield self.seq.frame(k)

    def poses(self) -> np.ndarray:
        """All frame poses [N, 4, 4] straight from ``traj.txt`` (no image is read)."""
        return self.seq.poses[self.ks].copy()


class BagFrameSource(FrameSource):
    """Frames of a rosbag2 bag (folder or ``.mcap``): the topics, transports and pose source of ``topics``."""

    kind = "bag"

    def __init__(
        self,
        path: Path,
        size: tuple[int | None, int | None] | None,
        stride: int,
        max_frames: int | None,
        topics: CameraTopics | None = None,
    ) -> None:
        self.stride, self.max_frames, self.size = stride, max_frames, size
        self.topics = topics or CameraTopics()
        native = None
        with BagReader(path, self.topics) as reader:
            for bf in reader.frames():
                native = bf.intrinsics
                break
            n_total = reader.message_count() // len(reader.topics.types())  # one message per topic and frame
            why = f" (no pose on TF: {reader.last_tf_error})" if reader.no_tf else ""
        if native is None:
            raise InputError(path, f"bag holds no complete RGB-D frame{why}")
        self.native = native
        n = len(range(0, n_total, stride))
        n = min(n, max_frames) if max_frames is not None else n
        intr = native.resized(*size) if size is not None else native
        mesh = (path if path.is_dir() else path.parent) / "mesh.ply"
        super().__init__(path, intr, n, mesh if mesh.is_file() else None)

    def __iter__(self) -> Iterator[Frame]:
        with BagReader(self.path, self.topics) as reader:
            emitted = 0
            for i, bf in enumerate(reader.frames()):
                if self.max_frames is not None and emitted >= self.max_frames:
                    break
                if i % self.stride:
                    continue
                if (bf.intrinsics.width, bf.intrinsics.height) != (self.native.width, self.native.height):
                    raise InputError(
                        f"{self.path} frame {i}",
                        f"image size {bf.intrinsics.width}x{bf.intrinsics.height} changed from "
                        f"{self.native.width}x{self.native.height}",
                    )
                frame = Frame(index=i, rgb=bf.rgb, depth_m=bf.depth_m, T_wc=bf.T_wc)
                emitted += 1
                yield resize_frame(frame, self.intrinsics)


class MemoryFrameSource(FrameSource):
    """Frames already in memory (e.g. received over ROS 2), in arrival order."""

    kind = "memory"

    def __init__(self, frames: list[Frame], intrinsics: Intrinsics, origin: str, gt_mesh_path: Path | None = None):
        if not frames:
            raise InputError(origin, "no frames")
        super().__init__(Path(origin), intrinsics, len(frames), gt_mesh_path)
        self.frames = frames

    def __iter__(self) -> Iterator[Frame]:
        return iter(self.frames)


def _is_bag(path: Path) -> bool:
    if path.is_file():
        return path.suffix == ".mcap"
    return (path / "metadata.yaml").is_file() or (
        not (path / "results").is_dir() and len(list(path.glob("*.mcap"))) == 1
    )


def open_frames(
    path: str | Path,
    size: tuple[int | None, int | None] | None = None,
    stride: int = 1,
    max_frames: int | None = None,
    allow_partial: bool = False,
    topics: CameraTopics | None = None,
) -> FrameSource:
    """A :class:`FrameSource` over a bag or Replica folder; ``size`` = (width, height) resizes on load.

    One side of ``size`` may be None: it follows the source's aspect ratio.

    ``stride`` keeps every stride-th frame, ``max_frames`` caps the count after the stride;
    ``allow_partial`` lets a Replica ``traj.txt`` hold more poses than frames on disk; ``topics`` says
    how a bag is read (topic names, transports, pose from a topic or TF; ignored for a folder).
    """
    path = Path(path)
    if not path.exists():
        raise InputError(path, "no such bag or scene folder")
    if int(stride) < 1:
        raise InputError("--stride", f"must be at least 1, got {stride}")
    if max_frames is not None and int(max_frames) < 1:
        raise InputError("--max-frames", f"must be at least 1, got {max_frames}")
    if size is not None and any(v is not None and int(v) <= 0 for v in size):
        raise InputError("--width/--height", f"image size must be positive, got {size[0]}x{size[1]}")
    if _is_bag(path):
        return BagFrameSource(path, size, int(stride), max_frames, topics)
    return ReplicaFrameSource(path, size, int(stride), max_frames, allow_partial)


__all__ = [
    "BagFrameSource",
    "FrameSequence",
    "FrameSource",
    "MemoryFrameSource",
    "ReplicaFrameSource",
    "open_frames",
]
