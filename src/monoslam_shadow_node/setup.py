from glob import glob

from setuptools import find_packages, setup

package_name = 'monoslam_shadow_node'

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
    description='MonoSLAM with moving objects: the Shadow filter and its classifier',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'shadow_filter = monoslam_shadow_node.shadow_filter.node:main',
            'monoslam = monoslam_shadow_node.monoslam.node:main',
            'feature_tracker = monoslam_shadow_node.feature_tracker.node:main',
        ],
    },
)
