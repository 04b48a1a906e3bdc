"""The ROS 2 shell: topic QoS, parameters, message conversions and the nodes."""
