"""The one exception type for bad user input.

The CLI turns a :class:`GpmpcError` into one line on stderr and a non-zero exit
(no traceback unless ``--debug``); anything else is a bug and keeps its traceback.
"""

from __future__ import annotations


class GpmpcError(ValueError):
    """Bad input from a user: a file, a config value, a command-line argument.

    The message names the field and says how to fix it.

    Examples:
        >>> from torch_gpmpc import Config, GpmpcError
        >>> try:
        ...     Config().replace(horizn=10)
        ... except GpmpcError as err:
        ...     print(err)
        unknown config key 'horizn'; did you mean 'horizon'?
    """
