"""``python -m formopt_ros.ros.nodes --write-configs DIR``: the nodes' parameter files."""
import sys

from formopt_ros.ros.nodes import main

sys.exit(main())
