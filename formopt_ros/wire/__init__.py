"""What goes over the wire: topic table, message readers, run description (no ROS import)."""
