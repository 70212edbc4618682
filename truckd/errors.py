"""Error types that map onto the command line's exit codes (reference section 1)."""


class InputError(Exception):
    """Bad usage or bad input: the CLI prints the one-line message and exits 2.

    The message names the file, the line or key, and what was expected.
    """


class TruckdError(Exception):
    """Any other failure the CLI reports in one line and exits 1."""
