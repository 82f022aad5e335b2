from glob import glob

from setuptools import find_packages, setup

package_name = 'hdp_controller'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
    ],
    install_requires=[
        'setuptools',
        'hdp_motion',
        'hdp_msgs_py',
        'hdp_data',
        'hdp_learning',
        'hdp_ros',
        'numpy',
        'pyyaml',
        'tqdm',
        'torch',
        'pytorch-kinematics',
        'diffusers',
        'matplotlib',
        'ompl',
    ],
    extras_require={'test': ['pytest']},
    zip_safe=True,
    maintainer='HDP-ROS developers',
    maintainer_email='hdp-ros@example.com',
    description='RK-Diffuser low-level policy, baselines and controller_node',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'controller_node = hdp_controller.controller_node:main',
        ],
        'hdp.commands': [
            'train.low-level = hdp_controller.cli:configure_train',
        ],
    },
)
