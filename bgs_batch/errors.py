"""Errors users can act on: each carries a message naming the file and the fix, and an exit code.

Exit codes (documented in README):

- 0 success
- 1 unexpected internal error (a bug: please report it)
- 2 usage error (bad command line; Click's convention)
- 3 invalid input data (missing, unreadable or inconsistent files)
- 4 output already exists (pass ``--overwrite`` to replace it)
- 5 job directory in use by another process, or made for another store or settings
- 75 a job stopped by SIGTERM/SIGUSR1/SIGINT after checkpointing (run it again to continue)
- 128 + N interrupted by signal N (130 for Ctrl-C, 143 for SIGTERM); nothing half-written is left
"""


class BgsError(Exception):
    """Base class of errors that are reported to the user without a traceback."""

    exit_code = 1


class InputError(BgsError):
    """The input data is missing, unreadable or inconsistent."""

    exit_code = 3


class OutputExistsError(BgsError):
    """The output path exists and the user did not ask to overwrite it."""

    exit_code = 4


class Interrupted(BgsError):
    """Work was stopped by a signal; partial output has been removed."""

    def __init__(self, signum: int) -> None:
        import signal

        super().__init__(f"interrupted by {signal.Signals(signum).name}; partial output removed")
        self.exit_code = 128 + signum
