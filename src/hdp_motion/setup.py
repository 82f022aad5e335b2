from setuptools import find_packages, setup

package_name = 'hdp_motion'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools', 'numpy'],
    # kinematics needs torch; planning (IK, straight lines, RRT-Connect) PyBullet and OMPL.
    # Robot-side code that only times paths needs neither.
    extras_require={
        'kinematics': ['torch', 'pytorch-kinematics', 'pybullet'],
        'planning': ['pybullet', 'ompl'],
        'test': ['pytest'],
    },
    zip_safe=True,
    maintainer='HDP-ROS developers',
    maintainer_email='hdp-ros@example.com',
    description='The Franka Panda model, forward kinematics, trajectory timing and motion planning',
    license='Apache-2.0',
)
