"""Logging helpers for code that hostile or broken peers can make repeat itself.

`RateLimitedLog` logs the first occurrence of each key, then at most one line
per key per `interval_s`, saying how many were suppressed since the last line.
Its key table is an LRU of at most `max_keys` entries (`evicted` counts those
pushed out), so spoofed senders cannot grow it. Used by the server's ingest,
the station agent and the bridge (each vehicle's link and its back-channel).
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict
from typing import Callable, Hashable


class RateLimitedLog:
    """log(key, level, msg, *args): first line per key at once, then one per interval_s with a count."""

    def __init__(self, logger: logging.Logger, interval_s: float = 10.0, max_keys: int = 1024,
                 clock: Callable[[], float] = time.monotonic):
        self.logger = logger
        self.interval_s = float(interval_s)
        self.max_keys = int(max_keys)
        self.clock = clock
        self._keys: OrderedDict[Hashable, list] = OrderedDict()  # key -> [last logged at, suppressed since]
        self.suppressed = 0  # lines not logged, all keys, ever
        self.evicted = 0  # keys pushed out of the table

    def log(self, key: Hashable, level: int, msg: str, *args: object) -> bool:
        """Log unless this key logged less than interval_s ago; True when a line was written."""
        now = self.clock()
        entry = self._keys.get(key)
        if entry is None:
            if len(self._keys) >= self.max_keys:
                self._keys.popitem(last=False)
                self.evicted += 1
            self._keys[key] = [now, 0]
            self.logger.log(level, msg, *args)
            return True
        self._keys.move_to_end(key)
        if now - entry[0] < self.interval_s:
            entry[1] += 1
            self.suppressed += 1
            return False
        if entry[1]:
            msg += " (%d more like this in the last %.0f s)"
            args = (*args, entry[1], now - entry[0])
        entry[0], entry[1] = now, 0
        self.logger.log(level, msg, *args)
        return True

    def warning(self, key: Hashable, msg: str, *args: object) -> bool:
        """log(key, logging.WARNING, ...): the form callers that only warn pass around as a callable."""
        return self.log(key, logging.WARNING, msg, *args)

    def __len__(self) -> int:
        return len(self._keys)
