"""Bag input (rosbags), PointCloud2 and Livox CustomMsg decoding, the IMU/LiDAR sequencer and result writers."""

from adalio.io.bag import Bag
from adalio.io.bagwrite import BagWriter
from adalio.io.livox import LivoxCloud, LivoxDecoder
from adalio.io.pointcloud2 import CloudDecoder, decode_pointcloud2, encode_pointcloud2
from adalio.io.sequencer import Sequencer
from adalio.io.writers import ScansCsvWriter, TumWriter, read_ply_points, read_tum, write_map

__all__ = ["Bag", "BagWriter", "CloudDecoder", "LivoxCloud", "LivoxDecoder", "ScansCsvWriter",
           "Sequencer", "TumWriter", "decode_pointcloud2", "encode_pointcloud2", "read_ply_points", "read_tum", "write_map"]
