"""The ROS 2 shell: topic QoS, parameters, message conversions and the nodes."""
from formopt_ros import one_blas_thread

one_blas_thread()
