"""The one exception of the bag layer."""


class BagError(Exception):
    """A bag (or bag request) that cannot be served; the text says why, for the user."""
