"""roigsf_ros: active mapping with 2D Gaussian surfels (ROI-GSurFisher).

The math lives in ROS-free layers, each a subpackage (docs/architecture.md): ``core`` (``core.camera``, ``core.frame``,
...), ``data`` (``data.replica``, ``data.scene``, ``data.bags``, ...), ``render``, ``evaluation``, ``mapping``, ``nbv``,
``policies`` and ``experiments``; ``roigsf_ros.nodes`` holds the thin ROS 2 adapters, ``roigsf_ros.cli`` the ``roigsf``
command.
"""

import os as _os
import sys as _sys
import warnings as _warnings

# torch's OpenMP workers spin between ops and starve the renderer's numba threads (3-4x slower
# mapping on 2 cores). The setting only works before torch is imported, so it is made here.
if "OMP_WAIT_POLICY" not in _os.environ:
    _os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
    if "torch" in _sys.modules:
        # scripts/measure_nbv_stalls.py: a float32 -> float64 conversion of 180k values, beside one busy process.
        _warnings.warn(
            "roigsf_ros: torch was imported before roigsf_ros with OMP_WAIT_POLICY unset, so its OpenMP threads "
            "spin-wait and stall the renderer's threads on shared cores (small torch ops many times slower); "
            "import roigsf_ros first or set OMP_WAIT_POLICY=PASSIVE in the environment",
            RuntimeWarning,
            stacklevel=2,
        )

__version__ = "0.1.0"
__all__ = ["__version__"]  # the subpackages are the API: import roigsf_ros.nbv, roigsf_ros.mapping, ...
