from glob import glob

from setuptools import find_packages, setup

package_name = 'marker_detector'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='dynamic-slam maintainers',
    maintainer_email='dev@example.com',
    description=(
        'Fiducial detection (cv2.aruco), and apriltag_ros detections, to range-bearing '
        'landmark observations'
    ),
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'marker_detector = marker_detector.detector.node:main',
            'marker_detector_lifecycle = marker_detector.detector.lifecycle:main',
            'marker_detect_bag = marker_detector.detector.offline:main',
            'apriltag_bridge = marker_detector.apriltag_bridge.node:main',
        ],
    },
)
