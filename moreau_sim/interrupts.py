"""SIGINT and SIGTERM for the command line (docs/cli.md, "Exit status"): during start-up (the
imports) a signal ends the process with one line; once a command runs, both raise
KeyboardInterrupt so that what was computed is kept, and the exit status names the signal."""

from __future__ import annotations

import contextlib
import os
import signal
import threading

EXIT_STATUS = {signal.SIGINT: 130, signal.SIGTERM: 143}  # 128 + the signal's number, as a shell reports it
_received: list[int] = []


def _quit(signum, frame):  # nothing computed yet: nothing to keep
    os.write(2, f"moreau-sim: interrupted by {signal.Signals(signum).name} during start-up\n".encode())
    os._exit(EXIT_STATUS[signum])


def _raise(signum, frame):
    _received.append(signum)
    raise KeyboardInterrupt


def during_startup() -> None:
    """SIGINT or SIGTERM ends the process at once with one line (no traceback from an import)."""
    for s in EXIT_STATUS:
        signal.signal(s, _quit)


def raising() -> dict:
    """SIGINT and SIGTERM raise KeyboardInterrupt (the commands save what they have and exit);
    returns the handlers they had, for :func:`restore`."""
    _received.clear()
    return {s: signal.signal(s, _raise) for s in EXIT_STATUS}


def restore(previous: dict) -> None:
    for s, handler in previous.items():
        signal.signal(s, handler)


def signal_name() -> str:
    """The last signal received (SIGINT when none was: a KeyboardInterrupt from the terminal)."""
    return signal.Signals(_received[-1] if _received else signal.SIGINT).name


def exit_status() -> int:
    """130 after SIGINT (or Ctrl-C), 143 after SIGTERM."""
    return EXIT_STATUS[_received[-1]] if _received else 130


@contextlib.contextmanager
def held():
    """SIGINT and SIGTERM held back while a file is written (main thread; a handler set from Python), then
    delivered to the handler they had: the KeyboardInterrupt they raise comes after the write, not inside
    zipfile's writer, which would close its archive half-written and replace the interrupt with an error of its
    own."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list[int] = []
    previous = {s: signal.getsignal(s) for s in EXIT_STATUS}
    previous = {s: h for s, h in previous.items() if h is not None}  # None: set outside Python, left alone
    for s in previous:
        signal.signal(s, lambda signum, frame: pending.append(signum))
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        for s in dict.fromkeys(pending):
            signal.raise_signal(s)
