"""Files in and out: ROS bags, scan files, mesh lists."""
