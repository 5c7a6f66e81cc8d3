"""rosbag2 MCAP bags: reading, writing, chunk copies, recovery, missions."""
