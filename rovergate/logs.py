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
