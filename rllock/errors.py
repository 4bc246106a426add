"""The one exception type the command line turns into a one-line error."""


class RLLockError(Exception):
    """Bad input or an impossible request; the message is shown to the user as is."""
