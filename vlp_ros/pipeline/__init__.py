"""The frame pipeline: one image to one pose (ROS-free), with its validated settings, counters and debug view."""
