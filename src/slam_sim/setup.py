from setuptools import find_packages, setup

package_name = 'slam_sim'

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
    description=(
        'Seeded simulated worlds and real-data importers for the dynamic-SLAM suite, '
        'written as rosbag2 bags'
    ),
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'office_sim = slam_sim.office_bag:main',
            'office_camera_sim = slam_sim.office_camera_bag:main',
            'dynamic_features_sim = slam_sim.dynamic_features_bag:main',
            'dynamic_camera_sim = slam_sim.dynamic_camera_bag:main',
            'victoria_park_import = slam_sim.victoria_park_bag:main',
            'mrclam_import = slam_sim.mrclam_bag:main',
            'tum_rgbd_import = slam_sim.tum_rgbd_bag:main',
            'peoplebot_sim = slam_sim.peoplebot_sim_node:main',
            'route_driver = slam_sim.route_driver_node:main',
            'dynamic_scene_sim = slam_sim.dynamic_scene_sim_node:main',
            'label_gate = slam_sim.label_gate_node:main',
        ],
    },
)
