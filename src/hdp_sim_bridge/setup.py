from setuptools import find_packages, setup

package_name = 'hdp_sim_bridge'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=[
        'setuptools',
        'hdp_motion',
        'hdp_msgs_py',
        'hdp_data',
        'hdp_ros',
        'numpy',
        'pyyaml',
        'tqdm',
        'pybullet',
        'ompl',
        'opencv-python-headless',
    ],
    extras_require={'test': ['pytest']},
    zip_safe=True,
    maintainer='HDP-ROS developers',
    maintainer_email='hdp-ros@example.com',
    description='PyBullet Panda + D415 stand-in, tasks, scripted experts, sim_bridge_node',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'sim_bridge_node = hdp_sim_bridge.sim_bridge_node:main',
        ],
        'hdp.commands': [
            'collect = hdp_sim_bridge.cli:configure_collect',
            'render = hdp_sim_bridge.cli:configure_render',
            'bench.sim = hdp_sim_bridge.cli:configure_bench_sim',
        ],
    },
)
