from glob import glob

from setuptools import find_packages, setup

package_name = 'hdp_planner'

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
        'diffusers',       # hdp_planner.flat: Diffusion Policy's noise schedule and samplers
    ],
    extras_require={'test': ['pytest']},
    zip_safe=True,
    maintainer='HDP-ROS developers',
    maintainer_email='hdp-ros@example.com',
    description='HDP high-level agent (next-best pose) and planner_node',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'planner_node = hdp_planner.planner_node:main',
        ],
        'hdp.commands': [
            'train.high-level = hdp_planner.cli:configure_train',
            'eval.high-level-offline = hdp_planner.cli:configure_eval',
            'bench.language = hdp_planner.cli:configure_bench_language',
            'train.flat = hdp_planner.flat.cli:configure_train',
        ],
    },
)
