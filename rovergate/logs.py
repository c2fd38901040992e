"""One logging set-up for every process."""

from __future__ import annotations

import logging
import os
import sys


def init_logging(process_name: str, level: str | None = None) -> logging.Logger:
    """Configure stdlib logging to stderr with the process name in every line.

    The level comes from ``level``, else ``ROVERGATE_LOG`` (default ``INFO``).
    """
    level = (level or os.environ.get("ROVERGATE_LOG", "INFO")).upper()
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter(
        f"%(asctime)s {process_name:>8} %(levelname)-7s %(message)s", "%H:%M:%S"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level)
    return logging.getLogger(f"rovergate.{process_name}")


def plural(n: int, word: str, words: str | None = None) -> str:
    """``n`` and the word in its number: ``plural(1, "collision")`` is "1 collision",
    ``plural(2, "collision")`` "2 collisions"."""
    return f"{n} {word if n == 1 else (words or word + 's')}"


#: Dropped messages logged one by one, then one in this many (a flood of bad messages must
#: not fill the disk with log lines; every one is still counted).
DROP_LOG_FIRST = 20
DROP_LOG_EVERY = 1000


def log_drop(log: logging.Logger, count: int, what: str, where: str, why: object) -> None:
    """Log the ``count``-th dropped message (the first DROP_LOG_FIRST, then every
    DROP_LOG_EVERY-th, saying so)."""
    if count <= DROP_LOG_FIRST:
        log.warning("dropped a %s on %s: %s (%d dropped so far)", what, where, why, count)
    elif count % DROP_LOG_EVERY == 0:
        log.warning("dropped a %s on %s: %s (%d dropped so far; logging one in %d)", what,
                    where, why, count, DROP_LOG_EVERY)
