"""Offline analysis of recorded runs: re-estimation, report, figures (no rclpy)."""
