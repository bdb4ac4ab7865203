"""Progress bars that suit where they are drawn: live on a terminal; off one (a log file, CI),
a line at most every 30 seconds instead of a flood of carriage returns."""

from __future__ import annotations

import sys


def progress_bar(**kwargs):
    """A `tqdm.auto.tqdm` bar on stderr; off a terminal it refreshes at most every 30 s."""
    from tqdm.auto import tqdm

    stream = kwargs.setdefault("file", sys.stderr)
    terminal = bool(getattr(stream, "isatty", lambda: False)())
    if not terminal:
        kwargs.setdefault("mininterval", 30.0)
        kwargs.setdefault("maxinterval", 60.0)
        kwargs.setdefault("ncols", 80)
    else:
        kwargs.setdefault("dynamic_ncols", True)
    return tqdm(**kwargs)
