"""ament_python package for ptm_ros (works with `pip install .` and with colcon)."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "ptm_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    package_data={PACKAGE: ["py.typed", "schema/*.json"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (
            f"share/{PACKAGE}/config",
            sorted(glob("config/*.yaml") + glob("config/*.xml") + glob("config/*.rviz")),
        ),
        (f"share/{PACKAGE}/bags", sorted(glob("bags/*.json"))),
        *[(f"share/{PACKAGE}/{d}", sorted(glob(f"{d}/*"))) for d in sorted(glob("bags/*/"))],
    ],
    # the Python dependencies of every module (ROS 2 itself, rclpy and the messages, come from the ROS
    # install or the ros-jazzy-* wheels of requirements.txt; package.xml lists them for rosdep; OpenCV
    # too: apt's python3-opencv or requirements.txt's opencv-python-headless, not a second cv2 here)
    install_requires=[
        "setuptools",
        "numpy",
        "scipy",
        "pyyaml",
        "matplotlib",
        "tqdm",
        "rosbags>=0.11",
        "kiss-icp>=1.3",
    ],
    zip_safe=True,
    maintainer="ptm_ros maintainers",
    maintainer_email="maintainers@ptm-ros.dev",
    description="Probabilistic Topological Maps for ROS 2 (RBPF / MCMC over set partitions)",
    license="Apache-2.0",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": [
            "ptm-convert = ptm_ros.tools.convert:main",
            "ptm-sim = ptm_ros.tools.sim:main",
            "ptm-run = ptm_ros.tools.run:main",
            "ptm-eval = ptm_ros.tools.evaluate:main",
            "ptm-calibrate = ptm_ros.tools.calibrate:main",
            "ptm-bringup = ptm_ros.tools.bringup:main",
            "ptm-bag-player = ptm_ros.nodes.bag_player:main",
            "landmark_detector = ptm_ros.nodes.landmark_detector:main",
            "topology_filter = ptm_ros.nodes.topology_filter:main",
            "map_publisher = ptm_ros.nodes.map_publisher:main",
        ],
    },
)
