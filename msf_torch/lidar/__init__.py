"""2D LiDAR front end: point-to-line ICP between scans, scan odometry as a pose source, and
occupancy-grid maps."""
