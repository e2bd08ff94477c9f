"""Ctrl-C held off while a forkserver preloads: name this module first in a preload list and
:mod:`perception.preload_guard_end` last.

Python's forkserver ignores SIGINT only once its preload is done. An interrupt in the second or so before killed the
server with a KeyboardInterrupt traceback on the user's terminal, beside the parent's own message (the parent is the
one that handles an interrupt). The handler in force before is put back at the end, so the server's children start
with the handler they would have had.
"""

from __future__ import annotations

import signal
import threading

#: The SIGINT handler this module replaced (put back by :mod:`perception.preload_guard_end`); None: none replaced
#: (imported off the main thread, or a handler installed outside Python, which cannot be put back).
previous = None
if threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGINT) is not None:
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
