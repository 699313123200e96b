"""The one exception type the CLI turns into a clear one-line message and exit code 2."""


class StereoseedError(Exception):
    """Bad input or a degenerate configuration; the message names the input and what to do."""
