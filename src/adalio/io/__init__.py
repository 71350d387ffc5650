"""Bag input (rosbags), PointCloud2 decoding, the IMU/LiDAR sequencer and result writers."""
