"""rosbag2 recordings for playback: reading and validating bags, and what a replay plays when."""
