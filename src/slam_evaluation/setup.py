from setuptools import find_packages, setup

package_name = 'slam_evaluation'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='dynamic-slam maintainers',
    maintainer_email='dev@example.com',
    description='Evaluators, metrics, reports and plots of both papers of the dynamic-SLAM suite',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'em_sam_evaluate = slam_evaluation.em_sam_evaluate:main',
            'em_sam_sessions_evaluate = slam_evaluation.em_sam_sessions:main',
            'shadow_evaluate = slam_evaluation.shadow_evaluate:main',
            'monoslam_evaluate = slam_evaluation.monoslam_evaluate:main',
            'monoslam_image_evaluate = slam_evaluation.monoslam_image_evaluate:main',
            'monoslam_loop_evaluate = slam_evaluation.monoslam_loop_evaluate:main',
            'tum_rgbd_sequence = slam_evaluation.tum_sequence:main',
            'trajectory_evaluate = slam_evaluation.trajectory_evaluate:main',
            'classification_figure = slam_evaluation.classification_figure:main',
        ],
    },
)
