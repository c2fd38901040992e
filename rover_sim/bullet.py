"""pybullet, imported once without its banner: its C module prints "pybullet build time ..."
on import, which every command would otherwise show before its own output.
``from rover_sim.bullet import pb``."""

from __future__ import annotations

import ctypes
import os
import sys


def _import_quietly():  # the module object
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, 1)
        os.dup2(null, 2)
        import pybullet
        ctypes.CDLL(None).fflush(None)  # what C's stdio still buffers goes to /dev/null too
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in (*saved, null):
            os.close(fd)
    return pybullet


pb = _import_quietly()
