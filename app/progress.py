"""The terminal progress bar of ``tirdeflect process`` and ``record``: one that the work never depends on.

A bar writes to stderr, which may go away while the work goes on: a reader of a pipe that quit
(``2>&1 | head``, ``| less`` then ``q``), a terminal closed, or no stderr at all (``2>&-``: Python's
``sys.stderr`` is None). By-hand trial of 7 December 2026: ``tirdeflect record ... 2>&1 | head`` stopped the
recording at 9-11 of 50 frames with "[Errno 32] Broken pipe", said only to the pipe that had gone, and with
stderr closed it ended at once with exit 1 and no file. :func:`progress_bar` gives a bar that turns itself off
at the first write that fails.
"""

from __future__ import annotations

import sys

__all__ = ["progress_bar"]


class _Bar:
    """``update(n)`` and ``close()`` of a tqdm bar, or of nothing (``bar`` None); off for good after a failed write."""

    def __init__(self, bar=None):
        self._bar = bar

    def update(self, n: int = 1) -> None:
        if self._bar is not None:
            try:
                self._bar.update(n)
            except (OSError, ValueError, AttributeError):  # the stream has gone (EPIPE, EIO, closed, None)
                self._off()

    def close(self) -> None:
        if self._bar is not None:
            try:
                self._bar.close()
            except (OSError, ValueError, AttributeError):
                pass
            self._off()

    def _off(self) -> None:
        bar, self._bar = self._bar, None
        bar.disable = True  # (so that tqdm writes nothing more, at its close or when it is collected)


def progress_bar(total: int, *, desc: str | None = None, terminal_only: bool = True, disable: bool = False,
                 **options) -> _Bar:
    """A progress bar of ``total`` frames on stderr (tqdm), or one that shows nothing: ``disable``, no stderr,
    no tqdm, or (``terminal_only``) a stderr that is no terminal, so that log files stay clean."""
    stream = sys.stderr
    if disable or stream is None:
        return _Bar()
    try:
        from tqdm import tqdm
    except ImportError:  # pragma: no cover - tqdm is a dependency
        return _Bar()
    try:
        return _Bar(tqdm(total=total, desc=desc, unit="frame", file=stream, disable=None if terminal_only else False,
                         **options))
    except (OSError, ValueError, AttributeError):
        return _Bar()
