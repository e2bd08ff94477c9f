"""The end of :mod:`perception.preload_guard`: the SIGINT handler in force before it is back."""

from __future__ import annotations

import signal

from perception import preload_guard

if preload_guard.previous is not None:
    signal.signal(signal.SIGINT, preload_guard.previous)
