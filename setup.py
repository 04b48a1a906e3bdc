"""Build script of the formopt_ros ament_python package."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'formopt_ros'

setup(
    name=PACKAGE,
    version='0.2.0',
    packages=find_packages(exclude=['test', 'test.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
        ('share/' + PACKAGE + '/config', glob('config/*.yaml') + glob('config/*.xml')),
        ('share/' + PACKAGE + '/scripts', glob('scripts/*.sh')),
    ],
    python_requires='>=3.10',
    install_requires=['setuptools', 'numpy', 'scipy', 'PyYAML', 'mcap>=1.6', 'rosbags'],
    extras_require={
        'tools': ['matplotlib', 'tqdm'],
        'test': ['pytest', 'flake8', 'mypy'],
        'peers': ['casadi'],
        'sweep': ['dask[distributed]>=2024.8', 'matplotlib', 'tqdm'],
    },
    zip_safe=True,
    maintainer='formopt_ros developers',
    maintainer_email='dev@formopt.invalid',
    description='Optimized motion strategies for localization in leader-follower formations.',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'leader_sim = formopt_ros.ros.nodes.leader_sim:main',
            'follower_sim = formopt_ros.ros.nodes.follower_sim:main',
            'estimator_planner = formopt_ros.ros.nodes.estimator_planner:main',
            'follower_estimator = formopt_ros.ros.nodes.follower_estimator:main',
            'field_sim = formopt_ros.ros.nodes.field_sim:main',
            'recorder = formopt_ros.ros.nodes.recorder:main',
            'replay = formopt_ros.cli.replay:main',
            'formopt-montecarlo = formopt_ros.cli.montecarlo:main',
            'formopt-bench = formopt_ros.cli.bench:main',
            'formopt-bench-ros = formopt_ros.cli.bench_ros:main',
            'formopt-report = formopt_ros.cli.report:main',
            'formopt-bag = formopt_ros.cli.bag:main',
            'formopt-periodic = formopt_ros.cli.periodic:main',
            'formopt-sweep = formopt_ros.cli.sweep:main',
        ],
    },
)
