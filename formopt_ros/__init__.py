"""formopt_ros: optimized follower motion for localization in leader-follower formations."""
