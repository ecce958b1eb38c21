from glob import glob

from setuptools import find_packages, setup

package_name = 'em_sam_node'

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
    description='EM-SAM batch mapping with moveable-landmark detection',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'odometry_ingest = em_sam_node.odometry_ingest.node:main',
            'em_sam_mapper = em_sam_node.mapper.node:main',
            'em_sam_mapper_lifecycle = em_sam_node.mapper.lifecycle:main',
        ],
    },
)
