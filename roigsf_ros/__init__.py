"""roigsf_ros: active mapping with 2D Gaussian surfels (ROI-GSurFisher).

The math lives in ROS-free modules (``camera``, ``replica``, ``scene``, ``bags``, ``render``,
``mapping``, ``nbv``, ...); ``roigsf_ros.nodes`` holds the thin ROS 2 adapters.
"""

import os

# torch's OpenMP workers spin between ops and starve the renderer's numba threads (3-4x slower
# mapping on 2 cores). The setting only works before torch is imported, so it is made here.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
