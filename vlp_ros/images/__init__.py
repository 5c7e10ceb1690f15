"""Camera images as the detector takes them: serialized sensor_msgs/Image and CompressedImage, pixel formats."""
