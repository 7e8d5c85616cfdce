"""hdrqn_ros: an ament_python ROS 2 package and a pip-installable Python package at once."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "hdrqn_ros"
ROS_WHEELS = ["ros-jazzy-rclpy[fastrtps]", "ros-jazzy-rcl-interfaces", "ros-jazzy-builtin-interfaces",
              "ros-jazzy-ament-index-python", "ros-jazzy-std-msgs", "ros-jazzy-std-srvs", "ros-jazzy-sensor-msgs",
              "ros-jazzy-geometry-msgs", "ros-jazzy-nav-msgs", "ros-jazzy-rosgraph-msgs", "ros-jazzy-diagnostic-msgs",
              "ros-jazzy-visualization-msgs"]
"""The ``ros`` extra: exactly the ROS packages hdrqn_ros imports (test/test_packaging.py)."""

setup(
    name=PACKAGE,
    version="0.1.0",
    description="Hierarchical deep recurrent Q-learning (hDRQN) for ROS 2 and plain Python",
    long_description=open("README.md", encoding="utf-8").read(),
    long_description_content_type="text/markdown",
    license="Apache-2.0",
    python_requires=">=3.11",
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/launch", glob("launch/*.py")),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
        (f"share/{PACKAGE}/config/nav2", glob("config/nav2/*.yaml")),
        (f"share/{PACKAGE}/config/ros", glob("config/ros/*.yaml")),
    ],
    install_requires=[
        "numpy>=1.24",
        "gymnasium>=1.0",
        "ale-py>=0.9",
        "pyyaml>=6",
        "pydantic>=2",
        "tqdm>=4.60",
        "matplotlib>=3.7",
        "tensorboard>=2.14",
        "torch>=2.1",
        "rosbags>=0.10",
        "safetensors>=0.4",
        "mcap>=1.1",
        "mcap-ros2-support>=0.5",
    ],
    package_data={PACKAGE: ["dds/fastdds_loopback.xml"]},
    extras_require={
        "test": ["pytest>=8", "pytest-rerunfailures>=16.3", "hypothesis>=6.100", "onnxruntime>=1.17", "onnx>=1.15",
                 "ray>=2.9"],
        # hdrqn experiment NAME --ray: runs as Ray tasks (hdrqn_ros.cluster, docs/training.md "Cluster")
        "cluster": ["ray>=2.9"],
        # torch-free acting from an exported policy (hdrqn_ros.deploy, docs/deploy.md)
        "deploy": ["onnxruntime>=1.17", "onnx>=1.15"],
        # real ROS 2 Jazzy rclpy with rmw_fastrtps_cpp and the message packages the nodes use:
        # community-built wheels for Linux x86-64, CPython 3.10-3.13 (docs/security.md)
        "ros": ROS_WHEELS,
    },
    zip_safe=False,
    entry_points={
        "console_scripts": [
            "hdrqn = hdrqn_ros.cli:main",
            "environment = hdrqn_ros.nodes.executables:environment",
            "critic = hdrqn_ros.nodes.executables:critic",
            "meta_controller = hdrqn_ros.nodes.executables:meta_controller",
            "sub_controller = hdrqn_ros.nodes.executables:sub_controller",
            "learner = hdrqn_ros.nodes.executables:learner",
            "player = hdrqn_ros.nodes.executables:player",
            "robot_environment = hdrqn_ros.nodes.executables:robot_environment",
            "loopback_robot = hdrqn_ros.nodes.executables:loopback_robot",
        ],
    },
)
