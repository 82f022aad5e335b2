from setuptools import find_packages, setup

package_name = 'hdp_learning'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools', 'pyyaml'],
    # checkpoints and distributed import torch inside their functions only.
    extras_require={'torch': ['torch'], 'test': ['pytest']},
    zip_safe=True,
    maintainer='HDP-ROS developers',
    maintainer_email='hdp-ros@example.com',
    description='HDP-ROS learning infrastructure: --config, checkpoints, training curves, torchrun',
    license='Apache-2.0',
)
