"""Bad input in the `fit/` scripts: one line naming the problem, no traceback."""

from __future__ import annotations

import contextlib


@contextlib.contextmanager
def user_errors(prog: str):
    """Turn a `ValueError` or `OSError` raised inside into `SystemExit("prog: error: ...")`.

    dofjax's readers and checks raise these for bad input (a missing or unreadable file, a file
    that is not an image, a bad value), with a message naming the file or the value; a script
    prints that message (exit status 1) instead of a traceback. Anything else still propagates
    with its traceback: it is a bug, not bad input.
    """
    try:
        yield
    except (ValueError, OSError) as e:
        raise SystemExit(f"{prog}: error: {e}") from None
