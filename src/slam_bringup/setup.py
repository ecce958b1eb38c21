from glob import glob

from setuptools import find_packages, setup

package_name = 'slam_bringup'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    package_data={'slam_bringup.dashboard': ['web/*']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
        ('share/' + package_name + '/config', glob('config/*')),
        ('share/' + package_name + '/graphs', glob('graphs/*.yaml')),
        ('share/' + package_name + '/rviz', glob('rviz/*.rviz')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='dynamic-slam maintainers',
    maintainer_email='dev@example.com',
    description='Bag tools, graph runner, launch files and test harness of the dynamic-SLAM suite',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'bag_player = slam_bringup.bag_player:main',
            'bag_recorder = slam_bringup.bag_recorder:main',
            'bag_info = slam_bringup.bag_info:main',
            'bag_recover = slam_bringup.bag_recover:main',
            'slam_run = slam_bringup.runner:main',
            'slam_echo = slam_bringup.topic_echo:main',
            'slam_diag = slam_bringup.diag_monitor:main',
            'slam_call = slam_bringup.service_call:main',
            'slam_dashboard = slam_bringup.dashboard.node:main',
            'camera_mount = slam_bringup.camera_mount:main',
            'peoplebot_graph = slam_bringup.peoplebot:main',
        ],
    },
)
