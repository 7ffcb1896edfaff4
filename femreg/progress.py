"""Progress on stderr: a tqdm bar on a terminal, plain occasional lines elsewhere.

A bar redraws itself with carriage returns, which a log file or a pipe keeps as one long line of junk.  When
stderr is not a terminal, :func:`bar` returns a :class:`LineProgress` instead: one line when the count passes
each further tenth of the total (:data:`LINE_STEP`), or when :data:`LINE_SECONDS` have passed since the last line,
and one when it closes.  Both take the calls femreg makes on a bar (``update``, ``set_postfix_str``,
``refresh``, ``close``, ``n``, ``total``).
"""
from __future__ import annotations

import sys
import time

__all__ = ["bar", "iterate", "LineProgress", "stderr_is_terminal", "LINE_STEP", "LINE_SECONDS"]

#: A line each time the count passes a further fraction of the total.
LINE_STEP = 0.1
#: At the latest this many seconds after the last line, a line on the next call (long single steps).
LINE_SECONDS = 30.0


def stderr_is_terminal() -> bool:
    """True when stderr is an interactive terminal (False for a file, a pipe, a replaced or closed stream)."""
    try:
        return bool(sys.stderr.isatty())
    except (AttributeError, ValueError):
        return False


class LineProgress:
    """tqdm's interface, written as plain lines ``desc: n/total unit (p %), t s[, postfix]`` on stderr."""

    def __init__(self, total=None, desc: str = "", unit: str = "it", **_ignored):
        self.total = None if total is None else int(total)
        self.desc, self.unit, self.n, self.postfix = desc, unit, 0, ""
        self.start = self.last_time = time.monotonic()
        self.last_step = 0
        self.closed = False
        self.said = None                 # (n, total, postfix) of the last line

    def _line(self, final: bool = False) -> None:
        now = time.monotonic()
        frac = f" ({100.0 * self.n / self.total:.0f} %)" if self.total else ""
        total = f"/{self.total}" if self.total is not None else ""
        unit = self.unit if self.n == 1 or self.unit.endswith("s") else self.unit + "s"
        text = (f"{self.desc}: {'done, ' if final else ''}{self.n}{total} {unit}{frac}, "
                f"{now - self.start:.1f} s" + (f", {self.postfix}" if self.postfix else ""))
        try:
            print(text, file=sys.stderr, flush=True)
        except (ValueError, OSError):    # a closed stream: progress is a courtesy
            pass
        self.last_time = now
        self.said = (self.n, self.total, self.postfix)

    def _maybe(self) -> None:
        step = int(self.n / (LINE_STEP * self.total) + 1e-9) if self.total else 0
        if step > self.last_step:
            self.last_step = step
            self._line()
        elif time.monotonic() - self.last_time >= LINE_SECONDS:
            self._line()

    def update(self, n: int = 1) -> None:
        self.n += int(n)
        self._maybe()

    def set_postfix_str(self, s: str = "", refresh: bool = True) -> None:
        self.postfix = str(s)
        if refresh and time.monotonic() - self.last_time >= LINE_SECONDS:
            self._line()

    def set_postfix(self, ordered_dict=None, refresh: bool = True, **kwargs) -> None:
        items = dict(ordered_dict or {}, **kwargs)
        self.set_postfix_str(", ".join(f"{k}={v}" for k, v in items.items()), refresh=refresh)

    def set_description(self, desc: str = "", refresh: bool = True) -> None:
        self.desc = str(desc)

    def refresh(self) -> None:
        pass

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            # nothing to say when the last line said it, or when there was nothing to do (a total of 0)
            if self.said != (self.n, self.total, self.postfix) and (self.total != 0 or self.n):
                self._line(final=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def bar(total=None, desc: str = "", unit: str = "it", **kwargs):
    """A progress bar over ``total`` steps: tqdm on a terminal, :class:`LineProgress` otherwise."""
    if stderr_is_terminal():
        from tqdm.auto import tqdm

        return tqdm(total=total, desc=desc, unit=unit, **kwargs)
    return LineProgress(total=total, desc=desc, unit=unit)


def iterate(items, desc: str = "", unit: str = "it"):
    """Yield from ``items`` with a progress :func:`bar` over them (closed at the end, or when the loop stops)."""
    items = list(items)
    b = bar(total=len(items), desc=desc, unit=unit)
    try:
        for item in items:
            yield item
            b.update(1)
    finally:
        b.close()
