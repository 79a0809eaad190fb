"""The simulation: PyBullet world, robot stand-in, LiDAR and beam patterns, ray casting, leg odometry,
IMU, route follower, top-view rendering."""
