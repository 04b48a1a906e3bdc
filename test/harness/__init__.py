"""Helpers shared by the test folders (imported as ``harness``: test/ is on sys.path)."""
