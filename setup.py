from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'vlp_ros'

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', [f'resource/{PACKAGE}']),
        (f'share/{PACKAGE}', ['package.xml', 'LICENSE']),
        (f'share/{PACKAGE}/config', glob('config/*.yaml') + glob('config/*.xml')),
        (f'share/{PACKAGE}/launch', glob('launch/*.launch.py')),
    ],
    # As in every ament_python package, dependencies are declared in package.xml
    # (rosdep) and, for the pip setup, in requirements/*.txt; never here.
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='vlp_ros developers',
    maintainer_email='dev@vlp-ros.invalid',
    description='Camera-based visible light positioning for ROS 2',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'locator = vlp_ros.nodes.locator:main',
            'replay = vlp_ros.nodes.replay:main',
            'survey = vlp_ros.nodes.survey:main',
        ],
    },
)
