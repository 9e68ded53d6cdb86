"""User-facing errors.

Anything a user can cause (unknown names, malformed files, unsupported scene features, NaN images,
impossible settings) raises :class:`UserError` with a one-line message that names the problem. The CLI
prints it on stderr as ``splitbench: error: <message>`` and exits with code 2, without a traceback.
"""


class UserError(Exception):
    """A problem with the user's input. The message is one line and names the offending thing."""

    exit_code = 2

    def __init__(self, message: str):
        super().__init__(" ".join(str(message).split()))
