# SPDX-License-Identifier: BSD-3-Clause
"""One small progress bar for the command line, over a known number of jobs (or seconds).

Library functions take a `ProgressFn` callback (`progress(done, total, note)`) and never
write to the terminal themselves; the CLI passes a `ProgressBar`, which draws on stderr:
redrawn in place on a terminal, one line per update (at most every `min_interval_s`, and
always the last) when stderr is a file or a pipe, as in CI logs. No dependency.
"""

from __future__ import annotations

import shutil
import sys
import time
from collections.abc import Callable
from typing import TextIO

ProgressFn = Callable[[int, int, str], None]
"""`progress(done, total, note)`: `done` of `total` jobs finished; `note` names the last."""


def _format_duration(seconds: float) -> str:
    s = max(0, round(seconds))
    if s < 3600:
        return f"{s // 60:d}:{s % 60:02d}"
    return f"{s // 3600:d}:{(s % 3600) // 60:02d}:{s % 60:02d}"


class ProgressBar:
    """A plain text bar `label [#####.....] 5/10 0:12<0:12 note` on a stream (stderr).

    Call it as a `ProgressFn`; use it as a context manager to end the line cleanly.
    """

    def __init__(
        self,
        label: str,
        stream: TextIO | None = None,
        width: int = 24,
        min_interval_s: float = 2.0,
        enabled: bool = True,
        unit: str = "",
    ) -> None:
        self.label = label
        self.unit = unit
        self._last_note = ""
        self.stream = stream if stream is not None else sys.stderr
        self.width = width
        self.min_interval_s = min_interval_s
        self.enabled = enabled
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._start = time.monotonic()
        self._first_done: int | None = None
        self._prev_done = 0
        self._last_draw = -float("inf")
        self._drawn_inline = False

    def render(self, done: int, total: int, note: str = "") -> str:
        """The bar as one line of text (no newline)."""
        frac = done / total if total > 0 else 1.0
        filled = min(self.width, round(frac * self.width))
        elapsed = time.monotonic() - self._start
        text = f"{self.label} [{'#' * filled}{'.' * (self.width - filled)}] {done}/{total}"
        text += f" {self.unit}" if self.unit else ""
        text += f" {_format_duration(elapsed)}"
        first = self._first_done if self._first_done is not None else done
        if 0 < done - first and done < total:
            rate = (done - first) / elapsed if elapsed > 0 else 0.0
            if rate > 0:
                text += f"<{_format_duration((total - done) / rate)}"
        if note:
            text += f" {note}"
        return text

    def __call__(self, done: int, total: int, note: str = "") -> None:
        if not self.enabled:
            return
        if self._first_done is None or done < self._prev_done:  # a new pass (next method)
            self._first_done = done
            self._start = time.monotonic()
        self._prev_done = done
        now = time.monotonic()
        last = done >= total
        new_note = self._tty and note != self._last_note  # e.g. "finishing": redraw in place
        if (not last and not new_note
                and now - self._last_draw < (0.1 if self._tty else self.min_interval_s)):
            return
        self._last_draw = now
        self._last_note = note
        line = self.render(done, total, note)
        if self._tty:
            cols = shutil.get_terminal_size((120, 24)).columns
            self.stream.write("\r" + line[: cols - 1].ljust(cols - 1))
            self._drawn_inline = not last
            if last:
                self.stream.write("\n")
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    def close(self) -> None:
        """End an in-place line left unfinished (interrupted run)."""
        if self._drawn_inline:
            self.stream.write("\n")
            self.stream.flush()
            self._drawn_inline = False

    def __enter__(self) -> ProgressBar:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
