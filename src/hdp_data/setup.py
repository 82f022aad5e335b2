from setuptools import find_packages, setup

package_name = 'hdp_data'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools', 'hdp_motion', 'hdp_msgs_py', 'numpy', 'pyyaml', 'rosbags'],
    extras_require={'test': ['pytest']},
    zip_safe=True,
    maintainer='HDP-ROS developers',
    maintainer_email='hdp-ros@example.com',
    description='HDP-ROS data: recorded episodes (rosbag2), keyframes, task instructions, the workspace',
    license='Apache-2.0',
)
