"""roigsf_ros: active mapping with 2D Gaussian surfels (ROI-GSurFisher).

The math lives in ROS-free modules (``camera``, ``replica``, ``scene``, ``bags``, ...);
``roigsf_ros.nodes`` holds the thin ROS 2 adapters.
"""

__version__ = "0.1.0"
