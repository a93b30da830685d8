"""Packaging of gcn_match_ros (ament_python; also pip-installable)."""
import glob
import os

from setuptools import find_packages, setup

PACKAGE = 'gcn_match_ros'
HERE = os.path.dirname(os.path.abspath(__file__))

data_files = [
    ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
    ('share/' + PACKAGE, ['package.xml']),
    ('share/' + PACKAGE + '/config', sorted(os.path.relpath(p, HERE) for p in glob.glob(os.path.join(HERE, 'config', '*.yaml')))),
    ('share/' + PACKAGE + '/launch', sorted(os.path.relpath(p, HERE) for p in glob.glob(os.path.join(HERE, 'launch', '*.launch.py')))),
]
# Sample bags shipped with the package (if any exist at build time). rosbag2 bags are
# directories (metadata.yaml + storage files), so keep their relative layout.
_bag_files = sorted(
    os.path.relpath(p, HERE)
    for p in glob.glob(os.path.join(HERE, 'bags', '**', '*'), recursive=True)
    if os.path.isfile(p))
_bag_dirs = {}
for _f in _bag_files:
    _bag_dirs.setdefault(os.path.join('share', PACKAGE, os.path.dirname(_f)), []).append(_f)
data_files += sorted(_bag_dirs.items())

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    package_data={PACKAGE: ['models/*.pt', 'models/*.json']},
    include_package_data=False,
    data_files=data_files,
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='gcn_match_ros developers',
    maintainer_email='dev@gcn-match-ros.invalid',
    description='Multi-camera keypoint matching with a graph neural network (ROS 2).',
    license='Apache-2.0',
    python_requires='>=3.10',
    entry_points={
        'console_scripts': [
            'gcn-match = gcn_match_ros.cli:main',
            'matcher_node = gcn_match_ros.ros.matcher_node:main',
            'lifecycle_matcher_node = gcn_match_ros.ros.matcher_node:lifecycle_main',
            'feature_node = gcn_match_ros.ros.feature_node:main',
            'visualizer_node = gcn_match_ros.ros.visualizer_node:main',
            'mapping_node = gcn_match_ros.ros.mapping_node:main',
            'bag_play = gcn_match_ros.ros.bag_play:main',
            'bag_record = gcn_match_ros.ros.bag_record:main',
            'match_consumer = gcn_match_ros.ros.example_consumer:main',
        ],
    },
)
