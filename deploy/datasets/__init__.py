"""Readers for recorded sensor datasets (real data replayed through the navigation core)."""


class DatasetError(ValueError):
    """A dataset file is missing, truncated or malformed; the message names file and reason."""
