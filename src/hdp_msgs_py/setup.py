from setuptools import find_packages, setup

package_name = 'hdp_msgs_py'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    # ROS .msg definitions travel with the code (hdp_msgs_py/interfaces/<ros_pkg>/msg/<Type>.msg).
    package_data={package_name: ['interfaces/**/*.msg']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools', 'hdp_motion', 'numpy', 'opencv-python-headless', 'pyyaml'],
    extras_require={'test': ['pytest']},
    zip_safe=True,
    maintainer='HDP-ROS developers',
    maintainer_email='hdp-ros@example.com',
    description='HDP-ROS messages (wire-identical to ROS 2), their CDR codec, conversions and topic names',
    license='Apache-2.0',
)
