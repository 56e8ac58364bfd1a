"""The RGB-D frame with its pose, the data type every layer passes around."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from roigsf_ros.core.camera import Intrinsics


@dataclass
class Frame:
    """One RGB-D frame with its pose."""

    index: int
    rgb: np.ndarray  # [H, W, 3] uint8
    depth_m: np.ndarray  # [H, W] float32 metres, 0 where invalid
    T_wc: np.ndarray  # [4, 4] float64 camera-to-world


def resize_frame(frame: Frame, intr: Intrinsics) -> Frame:
    """The frame resized to ``intr``'s size (colour by area averaging, depth by nearest neighbour).

    Depth uses ``INTER_NEAREST_EXACT``, which keeps pixel centres aligned as
    :meth:`Intrinsics.resized` assumes; plain ``INTER_NEAREST`` samples up to half a source block
    off (0.4 px at 1200 -> 240, a 4 mm median depth error on Replica).
    """
    size = (intr.width, intr.height)
    if frame.depth_m.shape[::-1] == size:
        return frame
    rgb = cv2.resize(frame.rgb, size, interpolation=cv2.INTER_AREA)
    depth = cv2.resize(frame.depth_m, size, interpolation=cv2.INTER_NEAREST_EXACT)
    return Frame(index=frame.index, rgb=rgb, depth_m=depth, T_wc=frame.T_wc)


def spread_indices(n: int, k: int) -> list[int]:
    """``min(k, n)`` indices into a sequence of ``n`` spread evenly from first to last, ascending, no repeats."""
    if n <= 0 or k <= 0:
        return []
    return sorted({round(float(x)) for x in np.linspace(0, n - 1, min(int(k), n))})


__all__ = ["Frame", "resize_frame", "spread_indices"]
