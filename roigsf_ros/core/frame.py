"""The RGB-D frame with its pose, the data type every layer passes around."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.errors import InputError

COLOUR_FLOAT_MAX = 1.001
"""The most a float colour value may be: floats are [0, 1] (a little over 1 is clipped, as noise may reach it); more is
an image in 0-255 given as floats, refused rather than clipped to white."""


@dataclass
class Frame:
    """One RGB-D frame with its pose."""

    index: int
    rgb: np.ndarray  # [H, W, 3] uint8
    depth_m: np.ndarray  # [H, W] float32 metres, 0 where invalid
    T_wc: np.ndarray  # [4, 4] float64 camera-to-world


def check_float_colour(rgb: np.ndarray, where: str) -> None:
    """InputError naming ``where`` when float colour values (non-finite ones aside) exceed :data:`COLOUR_FLOAT_MAX`:
    a 0-255 image given as floats, which clipping to [0, 1] would silently turn white.
    """
    a = np.asarray(rgb)
    top = float(a[np.isfinite(a)].max(initial=0.0))
    if top > COLOUR_FLOAT_MAX:
        raise InputError(where, f"colour floats reach {top:g}: floats must be in [0, 1] (0-255: give uint8)")


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


__all__ = ["COLOUR_FLOAT_MAX", "Frame", "check_float_colour", "resize_frame", "spread_indices"]
