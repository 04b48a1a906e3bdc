"""Thin argparse front ends of the package's commands (one error convention, see common)."""
from formopt_ros import one_blas_thread

one_blas_thread()
