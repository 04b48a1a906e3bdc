"""ROS 2 nodes of formopt_ros: thin rclpy shells around formopt_ros.core."""
