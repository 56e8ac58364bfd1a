"""ament_python build of roigsf_ros: library, `roigsf` CLI and ROS 2 nodes."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "roigsf_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    package_data={f"{PACKAGE}.nbv": ["kernel_signatures.json"]},  # the warm-up's kernel signatures (set-up reads them)
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
        (f"share/{PACKAGE}/config/recommended", glob("config/recommended/*.yaml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.py")),
        # the sample bag and its mesh: the demo's defaults, found from any folder (data.bags.sample_path)
        (f"share/{PACKAGE}/bags", ["bags/README.md", "bags/synth_room_mesh.ply"]),
        (f"share/{PACKAGE}/bags/synth_room", glob("bags/synth_room/*")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="roigsf_ros developers",
    maintainer_email="roigsf@example.org",
    description="Active mapping with 2D Gaussian surfels and ROI-GSurFisher next-best-view selection.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "roigsf = roigsf_ros.cli:main",
            "bag_player = roigsf_ros.nodes.console:bag_player",
            "mapper = roigsf_ros.nodes.console:mapper",
            "nbv_planner = roigsf_ros.nodes.console:nbv_planner",
            "keyframe_selector = roigsf_ros.nodes.console:keyframe_selector",
            "active_mapping = roigsf_ros.nodes.console:active_mapping",
        ],
    },
)
