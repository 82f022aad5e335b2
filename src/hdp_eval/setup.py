from setuptools import find_packages, setup

package_name = 'hdp_eval'

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
        'hdp_controller',
        'hdp_motion',
        'hdp_msgs_py',
        'hdp_data',
        'hdp_learning',
        'hdp_planner',
        'hdp_sim_bridge',
        'numpy',
        'tqdm',
        'torch',
        'matplotlib',
    ],
    extras_require={'test': ['pytest']},
    zip_safe=True,
    maintainer='HDP-ROS developers',
    maintainer_email='hdp-ros@example.com',
    description='Evaluation in the simulator: Tables 1 and 2, the controller bench, Fig. 4',
    license='Apache-2.0',
    entry_points={
        'hdp.commands': [
            'eval.low-level = hdp_eval.cli:configure',
            'eval.hierarchy = hdp_eval.cli:configure_hierarchy',
            'eval.ladder = hdp_eval.cli:configure_ladder',
            'plot.low-level = hdp_eval.cli:configure_plot',
            'plot.curves = hdp_eval.curves_plot:configure',
            'plot.sensor = hdp_eval.sensor_figure:configure',
            'eval.samples = hdp_eval.sample_quality:configure',
            'bench.controller = hdp_eval.bench:configure',
        ],
    },
)
