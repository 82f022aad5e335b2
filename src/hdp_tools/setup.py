from setuptools import find_packages, setup

package_name = 'hdp_tools'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools', 'hdp_learning', 'hdp_msgs_py', 'hdp_ros', 'numpy'],
    # cyclonedds: only `hdp bench transport --modes cyclone`.
    extras_require={'bench': ['cyclonedds'], 'test': ['pytest']},
    zip_safe=True,
    maintainer='HDP-ROS developers',
    maintainer_email='hdp-ros@example.com',
    description='The hdp command line (subcommands from every package) and general tools: topic, node, bench transport',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'hdp = hdp_tools.cli.main:main',
        ],
        # Every package adds `hdp` subcommands here; a dotted name is a nested
        # subcommand (bench.transport -> `hdp bench transport`).
        'hdp.commands': [
            'topic = hdp_tools.cli.topic:configure',
            'node = hdp_tools.cli.node:configure',
            'lifecycle = hdp_tools.cli.lifecycle:configure',
            'bench.transport = hdp_tools.cli.bench_transport:configure',
        ],
    },
)
