from glob import glob

from setuptools import find_packages, setup

package_name = 'hdp_bringup'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
        ('share/' + package_name + '/config', glob('config/*.yaml') + glob('config/*.rviz') + glob('config/*.json')),
    ],
    install_requires=[
        'setuptools',
        'hdp_controller',
        'hdp_motion',
        'hdp_msgs_py',
        'hdp_data',
        'hdp_ros',
        'hdp_planner',
        'hdp_sim_bridge',
        'numpy',
        'pyyaml',
        'matplotlib',
        'pillow',
        'rosbags',               # hdp demo --record
        'opencv-python-headless',
        'torch',
    ],
    extras_require={'test': ['pytest']},
    zip_safe=True,
    maintainer='HDP-ROS developers',
    maintainer_email='hdp-ros@example.com',
    description='Launch files, parameters, hdp launch and hdp demo for the HDP graph',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'lifecycle_manager = hdp_bringup.lifecycle_manager:main',
        ],
        'hdp.commands': [
            'launch = hdp_bringup.launch_cli:configure',
            'demo = hdp_bringup.demo.cli:configure',
            'bench.soak = hdp_bringup.soak:configure',
            'bench.stop = hdp_bringup.stop_bench:configure',
            'bench.link = hdp_bringup.link_bench:configure',
        ],
    },
)
