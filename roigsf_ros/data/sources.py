"""One way to read posed RGB-D frames for the mapper: a rosbag2 bag or a Replica-layout folder.

:func:`open_frames` returns a :class:`FrameSource` with the (possibly resized) intrinsics, a frame
count and re-iterable frames as :class:`roigsf_ros.data.replica.Frame`. Scene folders written by
``roigsf scene render/synth`` also carry the ground-truth ``mesh.ply``, exposed as ``gt_mesh_path``: a folder's or a
bag's is the one :func:`roigsf_ros.data.replica.scene_gt_mesh` finds (in it, or ``NAME_mesh.ply`` beside it).

A frame's ``index`` names it in its source, whatever was skipped: a Replica frame's number, or a bag
frame's position among all the bag's frames (the sorted distinct stamps of its colour topic), so a
frame the reader skips (incomplete, or no pose on TF) still takes its number and later ids stay those
of the bag.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Protocol

import numpy as np

from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.frame import Frame, resize_frame
from roigsf_ros.data.bags import BagReader, CameraTopics, header_stamp_ns, opened_bag
from roigsf_ros.data.replica import ReplicaSequence, scene_gt_mesh


class FrameSequence(Protocol):
    """What the mapper's offline loop needs: intrinsics, a frame count and re-iterable frames."""

    intrinsics: Intrinsics

    def __len__(self) -> int: ...

    def __iter__(self) -> Iterator[Frame]: ...


def check_frame_source(source: object, where: str = "source") -> None:
    """InputError naming ``where`` unless ``source`` is a :class:`FrameSequence` (a path given in its place failed deep
    in the work on a missing attribute).
    """
    if not all(hasattr(source, a) for a in ("intrinsics", "__len__", "__iter__")):
        hint = ": open a folder or bag with open_frames(path)" if isinstance(source, str | Path) else ""
        raise InputError(where, f"expected a frame sequence, got {type(source).__name__}{hint}")


class FrameSource:
    """Posed RGB-D frames from disk, re-iterable; ``len`` is the number of frames after stride and cap.

    A source that skips frames it cannot read (a bag: incomplete stamps, no pose on TF, messages that do not
    convert) yields fewer than ``len`` and counts them, of those the stride and cap keep, after each full pass:
    ``skipped_incomplete``, ``skipped_no_tf`` and why (``no_tf_reason``), ``skipped_refused`` and why
    (``refused_reason``); and the TF frames that changed parent (``tf_reparented``, ``tf_reparent_note``).
    """

    kind = "base"

    def __init__(self, path: Path, intrinsics: Intrinsics, n_frames: int, gt_mesh_path: Path | None) -> None:
        self.path = path
        self.intrinsics = intrinsics
        self.n_frames = n_frames
        self.gt_mesh_path = gt_mesh_path
        self.skipped_incomplete = 0
        """Frames skipped on the last full pass because a message of theirs is missing."""
        self.skipped_no_tf = 0
        """Frames skipped on the last full pass because TF never gave their pose."""
        self.no_tf_reason = ""
        """Why TF gave no pose (the last lookup error), when ``skipped_no_tf``."""
        self.skipped_refused = 0
        """Frames skipped on the last full pass because their messages did not convert (a bad image, sizes)."""
        self.refused_reason = ""
        """Why frames were refused, each distinct reason with its count, when ``skipped_refused``."""
        self.tf_reparented = 0
        """Times a TF frame changed parent on the last full pass (poses through it moved; ``tf_reparent_note``)."""
        self.tf_reparent_note = ""
        self.tf_child_frame_note = ""
        """Why the poses are not the images' (``tf_child_frame`` is another frame than theirs), else ""."""
        self.camera_topics: CameraTopics | None = None
        """How a bag's camera was read, resolved against the bag (transports found, pose source, TF frames); None for a
        folder. Outputs record it: a wrong choice (a TF frame that is not the camera's) shows there."""

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
        cam: str | Path | None = None,
    ) -> None:
        self.seq = ReplicaSequence(path, cam=cam, size=size, allow_partial=allow_partial)
        self.ks = list(range(0, len(self.seq), stride))[: max_frames if max_frames is not None else None]
        super().__init__(Path(path), self.seq.intrinsics, len(self.ks), scene_gt_mesh(self.seq.root))

    def __iter__(self) -> Iterator[Frame]:
        for k in self.ks:
            yield self.seq.frame(k)

    def poses(self) -> np.ndarray:
        """All frame poses [N, 4, 4] straight from ``traj.txt`` (no image is read)."""
        return self.seq.poses[self.ks].copy()


class BagFrameSource(FrameSource):
    """Frames of a rosbag2 bag (folder or ``.mcap``): the topics, transports and pose source of ``topics``.

    A frame's index is its position among all the bag's frames, the sorted distinct header stamps of the
    colour topic (a stamp without colour is no frame), counted once when the source is opened: frames the
    reader skips (incomplete, no pose on TF, refused: messages that do not convert, or images of another size
    than the first frame's) keep their numbers, so the stride, the cap and the ids of the frames given name bag
    frames. ``len`` counts the frames the stride and cap keep, those skipped too. Frames come in the bag's order:
    where their stamps go back, ids do too (``given_back`` counts those frames, ``first_given_back`` says where the
    first was); a frame whose stamp an earlier frame had is skipped (``skipped_repeated``).
    """

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
        with BagReader(path, self.topics, skip_refused=True) as reader:
            for bf in reader.frames():
                native = bf.intrinsics
                break
            resolved = reader.topics
            first_note = reader.child_frame_note  # set by the first posed frame: known before any pass
            why = f" (no pose on TF: {reader.last_tf_error})" if reader.no_tf else ""
            why += f" ({reader.refused} refused: {reader.refusal_reasons})" if reader.refused else ""
        if native is None:
            raise InputError(path, f"bag holds no complete RGB-D frame{why}")
        self.native = native
        self.stamps_ns, self.complete = _frame_stamps(path, resolved)
        kept = range(0, len(self.stamps_ns), stride)
        self.kept = kept[:max_frames] if max_frames is not None else kept
        """Indices of the bag frames given (those skipped too): every stride-th, at most ``max_frames``."""
        intr = native.resized(*size) if size is not None else native
        super().__init__(path, intr, len(self.kept), scene_gt_mesh(path))
        self.camera_topics = resolved
        self.tf_child_frame_note = first_note

    def index_of(self, stamp_ns: int) -> int:
        """The bag frame index of a frame's stamp (its position in the sorted colour stamps)."""
        i = int(np.searchsorted(self.stamps_ns, stamp_ns))
        if i >= len(self.stamps_ns) or int(self.stamps_ns[i]) != stamp_ns:
            raise InputError(self.path, f"frame at {stamp_ns} ns is not among the bag's colour stamps: bag changed?")
        return i

    def __iter__(self) -> Iterator[Frame]:
        last = self.kept[-1] if len(self.kept) else -1
        expected = {k for k in self.kept if self.complete[k]}  # what the reader should give, unless TF cannot
        given: set[int] = set()
        previous = -1
        self.given_back, self.first_given_back = 0, ""
        resized: list[int] = []
        resized_reason = ""
        with BagReader(self.path, self.topics, skip_refused=True) as reader:
            for bf in reader.frames():
                i = self.index_of(bf.stamp_ns)
                if i > last and reader.topics.uses_tf:
                    break  # posed frames come in stamp order: every kept one was given or skipped
                if i > last or i % self.stride:  # (the reader gives each stamp once)
                    continue
                expected.discard(i)
                if (bf.intrinsics.width, bf.intrinsics.height) != (self.native.width, self.native.height):
                    # A camera restarted with another profile: refused and counted as the nodes do, not the end of
                    # the run (the frames before and after it still map).
                    resized.append(i)
                    resized_reason = resized_reason or (
                        f"frame {i}'s image size {bf.intrinsics.width}x{bf.intrinsics.height} (at "
                        f"{bf.stamp_ns / 1e9:.3f} s) differs from the first frame's {self.native.width}x"
                        f"{self.native.height}"
                    )
                    if not expected:
                        break
                    continue
                given.add(i)
                if i < previous:
                    self.given_back += 1
                    if not self.first_given_back:
                        # with its stamp, as `bag info` says it (which numbers frames in the bag's order)
                        self.first_given_back = (
                            f"frame {i} (ids in stamp order) at {bf.stamp_ns / 1e9:.3f} s, after frame {previous}"
                        )
                previous = i
                yield resize_frame(Frame(index=i, rgb=bf.rgb, depth_m=bf.depth_m, T_wc=bf.T_wc), self.intrinsics)
                if not expected:
                    break  # the rest of the kept frames are incomplete
            refused = {self.index_of(stamp) for stamp in reader.refused_stamps}
            kept = set(self.kept)
            reasons = [reader.refusal_reasons] if any(k in kept for k in refused) else []
            refused |= set(resized)
            self.skipped_repeated = sum(1 for stamp in reader.repeated_stamps if self.index_of(stamp) in kept)
            missing = [k for k in self.kept if k not in given and k not in refused]
            incomplete = sum(1 for k in missing if not self.complete[k])
            self.skipped_incomplete, self.skipped_no_tf = incomplete, 0
            if reader.no_tf:  # complete frames not given: TF gave no pose (or the reader gave up waiting)
                self.skipped_no_tf = len(missing) - incomplete
            else:
                self.skipped_incomplete = len(missing)
            self.no_tf_reason = reader.last_tf_error if self.skipped_no_tf else ""
            self.tf_reparented, self.tf_reparent_note = reader.tf_reparented, reader.tf_reparent_note
            self.tf_child_frame_note = reader.child_frame_note
            self.skipped_refused = sum(1 for k in self.kept if k in refused)
            self.refused_reason = "; ".join([*reasons, *([resized_reason] if resized else [])])


def _frame_stamps(path: Path, topics: CameraTopics) -> tuple[np.ndarray, np.ndarray]:
    """Sorted distinct colour stamps [N] int64 ns of a bag, and [N] bool: the stamp has every frame topic's message.

    ``topics`` resolved against the bag (:meth:`CameraTopics.in_bag`). One pass over the frame topics' raw
    messages, header stamps only (nothing is deserialized).
    """
    types = topics.types()
    seen: dict[int, set[str]] = {}
    with opened_bag(path) as reader:
        conns = [c for c in reader.connections if types.get(c.topic) == c.msgtype]
        for conn, _, raw in reader.messages(connections=conns):
            try:
                stamp = header_stamp_ns(raw)
            except (struct.error, IndexError):
                raise InputError(f"{path}:{conn.topic}", "message too short to hold a header") from None
            seen.setdefault(stamp, set()).add(conn.topic)
    stamps = sorted(s for s, have in seen.items() if topics.color in have)
    complete = [len(seen[s]) == len(types) for s in stamps]
    return np.asarray(stamps, dtype=np.int64), np.asarray(complete, dtype=bool)


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


def is_bag(path: str | Path) -> bool:
    """Whether :func:`open_frames` reads ``path`` as a bag: a ``.mcap`` file, a rosbag2 folder, or a folder holding one
    ``.mcap`` and no Replica ``results/``; anything else is read as a Replica folder.
    """
    path = Path(path)
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
    cam: str | Path | None = None,
) -> FrameSource:
    """A :class:`FrameSource` over a bag or Replica folder; ``size`` = (width, height) resizes on load.

    One side of ``size`` may be None: it follows the source's aspect ratio. Both given, the picture takes that shape
    whatever the source's (the intrinsics follow: fx and fy scale apart), so a (height, width) pair squashes it.

    ``stride`` keeps every stride-th frame, ``max_frames`` caps the count after the stride;
    ``allow_partial`` lets a Replica ``traj.txt`` hold more poses than frames on disk; ``topics`` says
    how a bag is read (topic names, transports, pose from a topic or TF; ignored for a folder); ``cam`` is a Replica
    folder's camera file when it has no ``cam_params.json`` (a bag carries its camera_info: refused for a bag).
    """
    path = Path(path)
    if not path.exists():
        raise InputError(path, "no such bag or scene folder")
    if int(stride) < 1:
        raise InputError("stride (--stride)", f"must be at least 1, got {stride}")
    if max_frames is not None and int(max_frames) < 1:
        raise InputError("max_frames (--max-frames)", f"must be at least 1, got {max_frames}")
    if size is not None and any(v is not None and int(v) <= 0 for v in size):
        raise InputError("size (--width/--height)", f"image size must be positive, got {size[0]}x{size[1]}")
    if is_bag(path):
        if cam is not None:
            raise InputError(path, "is a bag: its camera_info gives the camera (cam=PATH is for a Replica folder)")
        return BagFrameSource(path, size, int(stride), max_frames, topics)
    return ReplicaFrameSource(path, size, int(stride), max_frames, allow_partial, cam)


__all__ = [
    "BagFrameSource",
    "FrameSequence",
    "FrameSource",
    "MemoryFrameSource",
    "ReplicaFrameSource",
    "check_frame_source",
    "is_bag",
    "open_frames",
]
