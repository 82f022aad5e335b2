from setuptools import find_packages, setup

package_name = 'hdp_msgs_py'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    # ROS .msg definitions travel with the code (hdp_msgs_py/interfaces/<ros_pkg>/msg/<Type>.msg),
    # and so does the Fast DDS profile ros.init() applies.
    package_data={package_name: ['interfaces/**/*.msg', 'config/*.xml']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools', 'hdp_motion', 'numpy', 'pyyaml', 'rosbags'],
    extras_require={'test': ['pytest']},
    zip_safe=True,
    maintainer='HDP-ROS developers',
    maintainer_email='hdp-ros@example.com',
    description='HDP-ROS messages, conversions, topic names, rclpy node helpers and the hdp CLI',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'hdp = hdp_msgs_py.cli.main:main',
        ],
        # Every package adds `hdp` subcommands here; a dotted name is a nested
        # subcommand (bench.transport -> `hdp bench transport`).
        'hdp.commands': [
            'topic = hdp_msgs_py.cli.topic:configure',
            'node = hdp_msgs_py.cli.node:configure',
            'bench.transport = hdp_msgs_py.cli.bench_transport:configure',
        ],
    },
)
