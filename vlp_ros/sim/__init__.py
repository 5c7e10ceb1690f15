"""Rolling-shutter frame simulator with exact ground truth, and rosbag2 recordings of it."""
