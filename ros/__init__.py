"""ROS 2 and Foxglove: what a ROS graph and Foxglove read and write, without a ROS install.

messages (vision_msgs/msg/Detection3DArray and visualization_msgs/msg/MarkerArray in CDR, type hashes),
pointcloud2 (sensor_msgs/msg/PointCloud2 -> points), scans (a PointCloud2 sample -> the sectors to send),
recordings (rosbag2 and MCAP -> scans), scene (boxes and points -> Foxglove messages) and live_view (a
Foxglove WebSocket server drawing each stream's latest sector). The wire facts of rmw_zenoh (key
expressions, attachments, liveliness tokens) are in contract/ros2.py; the bridge's transport (its zenoh
session, threads and the worker it submits to) is server/ros2_bridge.py. Imports contract, lidar and numpy
(rosbags, mcap and foxglove-sdk when first used: `pip install "phim[ros2]"`); nothing of model/, server/ or
clients/.
"""
