"""GauSem: one ament_python package, pip-installable too (see README)."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "gausem"

setup(
    name=PACKAGE,
    version="0.1.0",
    description="Online RGB-D semantic SLAM with semantic Gaussian-splatting submaps and loop closure (ROS 2 Jazzy)",
    license="Apache-2.0",
    python_requires=">=3.10",
    packages=find_packages(include=["gausem_core*", "msg_adapters*", "gausem_ros*"]),
    package_data={"gausem_core": ["data/assets/*", "native/*.cpp", "native/*.h", "semantics/*.txt"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/params", glob("params/*.yaml")),
        (f"share/{PACKAGE}/launch", glob("gausem_ros/launch/*.launch.py")),
    ],
    install_requires=["numpy", "torch", "opencv-python-headless", "PyYAML", "tqdm", "packaging", "matplotlib"],
    extras_require={
        "loop": ["gtsam>=4.3.0"],
        "faiss": ["faiss-cpu"],
        "dinov2": ["transformers"],
        "ade20k": ["ai-edge-litert"],
        "cuda": ["gsplat"],
        "bags": ["rosbags"],
        "viewer": ["rerun-sdk>=0.41,<0.42"],  # gausem_core.viewer; Rerun's API changes between minor versions
    },
    zip_safe=True,
    entry_points={
        "console_scripts": [
            "gausem = gausem_core.cli:main",
            "gausem-ros = gausem_ros.run_all:main",
            "gausem-launch = gausem_ros.launcher:main",
            "gausem-player = gausem_ros.player:main",
            "gausem-bag = gausem_ros.convert:main",
            "gausem-segmentation = gausem_ros.nodes.segmentation:main",
            "gausem-tracking-mapping = gausem_ros.nodes.tracking_mapping:main",
            "gausem-loop-detection = gausem_ros.nodes.loop_detection:main",
            "gausem-pose-graph = gausem_ros.nodes.pose_graph:main",
        ],
    },
)
