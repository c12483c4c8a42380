"""
Bag I/O without ROS.

rosbag2 MCAP writing (writer), threaded recording (recorder), reading and u/y pairing for
identification (reader, pairing), repair of interrupted recordings (repair) and replay timing
(player). See docs/bags.md.
"""
