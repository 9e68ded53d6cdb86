"""netsim's one error type.

Anything a caller can get wrong (an unknown profile, an impossible setting, a message of zero bytes, a send time
that goes backwards) raises :class:`NetsimError` with a one-line message naming the bad setting, so that nothing
downstream can hang or fail obscurely. It subclasses :class:`ValueError` so that code unaware of netsim can still
catch it as a bad value. netsim's CLI prints it as one line on stderr and exits with status 2.
"""


class NetsimError(ValueError):
    """A bad setting or request. The message is one line and names the offending setting."""

    exit_code = 2

    def __init__(self, message: str):
        # Collapse whitespace so that a message built from several lines still prints as one.
        super().__init__(" ".join(str(message).split()))
