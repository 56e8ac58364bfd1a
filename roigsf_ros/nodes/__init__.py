"""ROS 2 nodes: thin adapters between topics and the ROS-free library (``ros2 run roigsf_ros <node>``)."""
