"""Thin argparse front ends of the package's commands (one error convention, see common)."""
