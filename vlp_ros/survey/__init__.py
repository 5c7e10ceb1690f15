"""
Surveying the lamp map from a recording: lamp positions and marker angles from a drive under them.

ROS-free: ``recording`` reads a bag through the pipeline, ``estimation`` solves the pose graph,
``partial_map`` reads the partial params file and writes the surveyed one, ``report`` draws it.
"""
