"""Bad input in the `fit/` scripts: one line naming the problem, no traceback.

Exit statuses of every dofjax command (`dofjax`, `python -m fit.*`, `python -m data_gen`):
0 success; 1 a failure that is not the input's fault; 2 usage errors and bad input; 3 a fit that
ran but is not trustworthy (not converged, or not identifiable from the image).
"""

from __future__ import annotations

import contextlib
import sys

USAGE = 2
UNTRUSTED_FIT = 3


@contextlib.contextmanager
def user_errors(prog: str):
    """Turn a `ValueError` or `OSError` raised inside into `prog: error: ...` on stderr and exit
    status 2.

    dofjax's readers and checks raise these for bad input (a missing or unreadable file, a file
    that is not an image, a bad value), with a message naming the file or the value. Anything
    else still propagates with its traceback: it is a bug, not bad input.
    """
    try:
        yield
    except (ValueError, OSError) as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        raise SystemExit(USAGE) from None
