"""The frame pipeline: one image to one pose (ROS-free), its validated settings, counters, debug view and warm-up."""
