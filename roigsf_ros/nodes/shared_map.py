"""One surfel map shared by the nodes of one process: a Mapper behind a lock, with cheap snapshots.

ROS-free. The mapper node owns the writes (keyframe insertion and optimisation in short slices under
the lock); the planner and the selector read :meth:`SharedMapper.snapshot` (cloned tensors, so they
never see a half-written step and never hold the lock while they score). The map is created on the
first frame (its intrinsics), or by :meth:`SharedMapper.load`. Keyframe ids/poses of a loaded map
are kept: :attr:`MapSnapshot.keyframe_ids` lists the loaded ones first, then the ones added since
(:meth:`Mapper.map_keyframes`, which :meth:`Mapper.save` writes too).
"""

from __future__ import annotations

import contextlib
import json
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import open3d as o3d
from torch import Tensor

from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.fileio import atomic_dir, check_replaceable
from roigsf_ros.mapping.mapper import H_TRAIN_FILE, Mapper, MapperConfig, write_h_train, write_map_meta
from roigsf_ros.render.surfels import SurfelMap


@dataclass
class MapSnapshot:
    """A consistent copy of the shared map: nothing in it changes when the mapper goes on."""

    surfel_map: SurfelMap
    """Cloned, detached surfels."""
    h_train: dict[str, Tensor] | None
    """Cloned training Fisher (None when the mapper does not track it or it misses loaded keyframes)."""
    keyframe_ids: list[int]
    """Loaded keyframe ids first, then the keyframes added since (insertion order)."""
    keyframe_poses: np.ndarray
    """[K, 4, 4] camera-to-world, aligned with ``keyframe_ids``."""
    intrinsics: Intrinsics
    config: MapperConfig
    version: int
    """Bumped by every change of the shared map (insertion, optimisation slice, load)."""

    @property
    def n_surfels(self) -> int:
        """Number of surfels."""
        return len(self.surfel_map)


def same_camera(a: Intrinsics, b: Intrinsics) -> bool:
    """Whether two intrinsics describe the same pinhole image (size and K; the PNG depth scale is ignored)."""
    if (a.width, a.height) != (b.width, b.height):
        return False
    return bool(np.allclose([a.fx, a.fy, a.cx, a.cy], [b.fx, b.fy, b.cx, b.cy], rtol=1e-9, atol=1e-9))


def view_mapper(surfel_map: SurfelMap, intr: Intrinsics, config: MapperConfig | None = None) -> Mapper:
    """A throw-away Mapper holding ``surfel_map``: renders, meshes and saves it without touching the shared one."""
    cfg = replace(config or MapperConfig(), track_h_train=False)
    m = Mapper(intr, cfg)
    m.map = surfel_map.detach().to(device=m.device, dtype=m.dtype)
    return m


class SharedMapper:
    """A :class:`Mapper` plus an ``RLock`` and a version counter; see the module docstring."""

    def __init__(self, config: MapperConfig | None = None) -> None:
        self.config = config or MapperConfig()
        self.lock = threading.RLock()
        """Held by every read and write of :attr:`mapper`; keep each hold short."""
        self.mapper: Mapper | None = None
        self.version = 0
        self._readers_waiting = 0
        self._count_lock = threading.Lock()
        self._answering = 0

    @contextlib.contextmanager
    def reading(self) -> Iterator[None]:
        """Hold :attr:`lock` as a reader: the writer's :meth:`yield_to_readers` lets waiting readers go first."""
        with self._count_lock:
            self._readers_waiting += 1
        try:
            self.lock.acquire()
        finally:
            with self._count_lock:
                self._readers_waiting -= 1
        try:
            yield
        finally:
            self.lock.release()

    def yield_to_readers(self, timeout_s: float = 5.0) -> None:
        """Called by the writer between two slices (lock not held): wait until no reader waits for the lock.

        Locks are not fair: a writer that re-acquires at once would starve the readers for a whole
        optimisation run.
        """
        deadline = time.monotonic() + timeout_s
        while self._readers_waiting > 0 and time.monotonic() < deadline:
            time.sleep(0.001)

    @contextlib.contextmanager
    def answering(self) -> Iterator[None]:
        """Mark a latency-bound read in progress (the planner answering a request): see :meth:`yield_to_answers`."""
        with self._count_lock:
            self._answering += 1
        try:
            yield
        finally:
            with self._count_lock:
                self._answering -= 1

    def yield_to_answers(self, max_s: float, stop: Callable[[], bool] | None = None) -> float:
        """Called by the writer between two slices: pause while a request is being answered, at most ``max_s``.

        On shared cores the planner's answer is what a robot waits for, while the optimisation can lag and catch
        up: without the pause the two split the cores and the answer comes about twice as late. ``stop()`` true
        ends the pause at once (a node shutting down). Returns the seconds paused.
        """
        t0 = time.monotonic()
        while self._answering > 0 and time.monotonic() - t0 < max_s and not (stop is not None and stop()):
            time.sleep(0.002)
        return time.monotonic() - t0

    # ----------------------------------------------------------------------------- writing
    def ensure(self, intr: Intrinsics) -> Mapper:
        """The mapper, created with ``intr`` on first use; InputError if ``intr`` differs from the map's."""
        with self.lock:
            if self.mapper is None:
                self.mapper = Mapper(intr, self.config)
                self.version += 1
            elif not same_camera(self.mapper.intr, intr):
                raise InputError("camera_info", f"intrinsics {intr} differ from the map's {self.mapper.intr}")
            return self.mapper

    def touch(self) -> None:
        """Record that the map changed (call under :attr:`lock` after writing to :attr:`mapper`)."""
        self.version += 1

    def load(self, directory: str | Path, expect_intr: Intrinsics | None = None) -> Mapper:
        """Replace the map with a saved one (keeping its keyframe ids/poses); InputError on a bad folder."""
        loaded = Mapper.load(directory, self.config)
        if expect_intr is not None and not same_camera(loaded.intr, expect_intr):
            raise InputError(directory, f"saved intrinsics {loaded.intr} differ from the camera's {expect_intr}")
        with self.lock:
            self.mapper = loaded
            self.version += 1
        return loaded

    # ----------------------------------------------------------------------------- reading
    @property
    def ready(self) -> bool:
        """Whether there is a map with at least one keyframe and one surfel."""
        with self.lock:
            m = self.mapper
            return m is not None and m.n_surfels > 0 and self._n_keyframes(m) > 0

    @staticmethod
    def _n_keyframes(m: Mapper) -> int:
        return len(m.loaded_keyframe_ids) + len(m.keyframes)

    @staticmethod
    def _ids_poses(m: Mapper) -> tuple[list[int], np.ndarray]:
        """Every keyframe of the map, loaded first: :meth:`Mapper.map_keyframes`, which the library's save writes."""
        return m.map_keyframes()

    def h_train_to_save(self) -> bool:
        """Whether a save writes the map's training Fisher (:attr:`Mapper.h_train_to_save`: computed or read before), so
        that a run that never read it does not pay one Fisher pass per keyframe to save it.
        """
        with self.reading():
            return self.mapper is not None and self.mapper.h_train_to_save

    def keyframe_ids(self) -> list[int]:
        """All keyframe ids (loaded first)."""
        with self.reading():
            return [] if self.mapper is None else self._ids_poses(self.mapper)[0]

    def snapshot(self, with_h_train: bool = True) -> MapSnapshot | None:
        """A consistent copy of the map (None before the first frame or load).

        ``h_train`` is included only when the mapper tracks it and it covers every keyframe (a map loaded without
        its saved ``h_train.npz`` lacks the loaded keyframes' Fisher: callers recompute it from the poses).
        """
        with self.reading():
            m = self.mapper
            if m is None:
                return None
            ids, poses = self._ids_poses(m)
            h = None
            if with_h_train and m.config.track_h_train and m.h_train_complete and self._n_keyframes(m):
                h = {k: v.detach().clone() for k, v in m.h_train.items()}
            return MapSnapshot(
                surfel_map=m.map.detach().clone(),
                h_train=h,
                keyframe_ids=ids,
                keyframe_poses=poses,
                intrinsics=m.intr,
                config=m.config,
                version=self.version,
            )

    # ----------------------------------------------------------------------------- outputs
    def save(
        self,
        directory: str | Path,
        with_mesh: bool = False,
        overwrite: bool = False,
        overwrite_hint: str | None = None,
    ) -> MapSnapshot:
        """Write map.ply + keyframes.json (+ mesh.ply) atomically from a snapshot (lock not held while writing).

        An existing ``directory`` without ``overwrite`` is a FileExistsError whose ``overwrite_hint`` tells the
        caller's user how to replace it (default: the command line's ``--overwrite``; :func:`atomic_dir`). With it, only
        an earlier map (or an empty folder) is replaced: a file or a folder of other things is refused, not deleted.
        """
        if overwrite:
            check_replaceable_map(directory)
        snap = self.snapshot(with_h_train=self.h_train_to_save())  # a resumed map then scores as this one
        if snap is None:
            raise InputError(directory, "nothing to save: the mapper has no map yet")
        with atomic_dir(directory, overwrite=overwrite, overwrite_hint=overwrite_hint) as tmp:
            save_snapshot(snap, tmp, with_mesh=with_mesh)
        return snap

    def mesh(self) -> tuple[o3d.geometry.TriangleMesh, MapSnapshot]:
        """The TSDF mesh of rendered depth at every keyframe pose, built from a snapshot (lock not held)."""
        snap = self.snapshot(with_h_train=False)
        if snap is None or snap.n_surfels == 0 or len(snap.keyframe_poses) == 0:
            raise InputError("map", "not ready: no keyframes or no surfels yet")
        return snapshot_mesh(snap), snap


def snapshot_mesh(snap: MapSnapshot) -> o3d.geometry.TriangleMesh:
    """TSDF + marching-cubes mesh of a snapshot's rendered depth at its keyframe poses (Mapper.mesh)."""
    return view_mapper(snap.surfel_map, snap.intrinsics, snap.config).mesh(list(snap.keyframe_poses))


def decimate_mesh(mesh: o3d.geometry.TriangleMesh, max_triangles: int) -> o3d.geometry.TriangleMesh:
    """``mesh`` with at most ``max_triangles`` triangles (0 = no limit), by vertex clustering (colours averaged).

    Vertex clustering is linear in the mesh size (quadric decimation takes ~10 s for 400k triangles).
    A surface of area A clustered at voxel s keeps about 2 A / s^2 triangles: the first voxel aims
    there, and each retry grows it by the excess ratio's square root (10% margin).
    """
    n = len(mesh.triangles)
    if max_triangles <= 0 or n <= max_triangles:
        return mesh
    area = max(float(mesh.get_surface_area()), 1e-12)
    voxel = float(np.sqrt(2.5 * area / max_triangles))
    out = mesh
    for _ in range(8):
        out = mesh.simplify_vertex_clustering(voxel_size=voxel)
        out.remove_degenerate_triangles()
        out.remove_unreferenced_vertices()
        if len(out.triangles) <= max_triangles:
            return out
        voxel *= 1.1 * float(np.sqrt(len(out.triangles) / max_triangles))
    raise InputError("mesh", f"could not decimate {n} triangles to {max_triangles}")


def is_saved_map(directory: str | Path) -> bool:
    """Whether ``directory`` is a saved map: a real folder (not a link) with ``keyframes.json``."""
    path = Path(directory)
    return path.is_dir() and not path.is_symlink() and (path / "keyframes.json").is_file()


def check_replaceable_map(directory: str | Path) -> None:
    """Refuse to replace anything at ``directory`` but a saved map (a folder with keyframes.json) or an empty folder:
    a mistyped ``overwrite: true`` save must not delete a file or a folder of other things.
    """
    check_replaceable(directory, ("keyframes.json",), "a saved map")


def save_snapshot(snap: MapSnapshot, directory: Path, with_mesh: bool = False) -> None:
    """Write a snapshot into an existing folder in :meth:`Mapper.save`'s layout (readable by :meth:`Mapper.load`),
    with ``h_train.npz`` when the snapshot carries it.
    """
    snap.surfel_map.save_ply(directory / "map.ply")
    write_map_meta(directory / "keyframes.json", snap.keyframe_ids, snap.keyframe_poses, snap.intrinsics, snap.config)
    if snap.h_train is not None:
        write_h_train(directory / H_TRAIN_FILE, snap.h_train)
    if with_mesh:
        mesh = snapshot_mesh(snap)
        if not o3d.io.write_triangle_mesh(str(directory / "mesh.ply"), mesh):
            raise OSError(f"{directory / 'mesh.ply'}: open3d could not write the mesh")


def read_keyframe_ids(directory: str | Path) -> list[int]:
    """Keyframe ids of a saved map folder (``keyframes.json``)."""
    path = Path(directory) / "keyframes.json"
    try:
        return [int(i) for i in json.loads(path.read_text())["keyframe_ids"]]
    except (OSError, KeyError, ValueError, TypeError) as exc:  # TypeError: not an object, or ids not a list
        raise InputError(path, f"cannot read keyframe ids: {exc}") from None


__all__ = [
    "MapSnapshot",
    "SharedMapper",
    "check_replaceable_map",
    "decimate_mesh",
    "is_saved_map",
    "read_keyframe_ids",
    "same_camera",
    "save_snapshot",
    "snapshot_mesh",
    "view_mapper",
]
