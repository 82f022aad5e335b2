from setuptools import find_packages, setup

package_name = 'hdp_ros'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    # The Fast DDS profiles ros.init() applies (and the OpenSSL settings of the TLS one) travel with the code.
    package_data={package_name: ['config/*.xml', 'config/*.cnf']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools', 'hdp_msgs_py'],
    extras_require={'test': ['pytest']},
    zip_safe=True,
    maintainer='HDP-ROS developers',
    maintainer_email='hdp-ros@example.com',
    description='What every HDP-ROS node adds to rclpy: the Fast DDS profile, Node, Status, run, liveness',
    license='Apache-2.0',
    entry_points={
        'hdp.commands': [
            'dds.credentials = hdp_ros.dds_cli:configure_credentials',
            'dds.server = hdp_ros.dds_cli:configure_server',
            'dds.env = hdp_ros.dds_cli:configure_env',
        ],
    },
)
