"""The module launcher: one process imports what every module needs, once, and forks each
module from there.

Four fresh interpreters each importing numpy, Zenoh, rosbags and tyro, and generating the
same message codecs, were most of the process set's start-up (about 0.45 s of CPU each, four
at once on two cores). The launcher does that work once, while the mission sets up its own
session, and a module forked from it imports only its own libraries (pybullet and trimesh,
torch, FCL and OMPL) on top.

Protocol (the mission's :class:`Launcher` is the only client): one JSON object a line on the
launcher's stdin, ``{"id": N, "argv": [...], "log": PATH, "append": bool}``, a module's
``mission.runtime.modules`` arguments; on its stdout ``{"id": N, "pid": P}`` once forked, and
``{"exit": P, "code": C}`` when a module exits (``C`` as :attr:`subprocess.Popen.returncode`
gives it: negative for a signal). When its stdin closes (the mission finished, or died), the
launcher exits and leaves its modules running: each stops on the mission's final status or
when the mission's liveliness token is gone, as a module started on its own would.

Nothing here comes from the network: the launcher's only input is the pipe from the mission
process that started it.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import select
import signal
import subprocess
import sys
import threading
import time
import traceback
from pathlib import Path
from typing import Any

from rovergate.errors import MissionFailed

log = logging.getLogger("rovergate.mission")

#: What every module imports (and the codecs of every topic, generated on import below).
PRELOAD = ("mission.runtime.modules", "rovergate.node", "scipy.spatial")

#: How long the mission waits for the launcher to fork a module.
SPAWN_TIMEOUT_S = 60.0


def module_args(argv: list[str]) -> list[str] | None:
    """The arguments of a command line of our own modules
    (``python -m mission.runtime.modules NAME ...``), or None for any other program (a user's
    planner)."""
    if argv[:3] == [sys.executable, "-m", "mission.runtime.modules"]:
        return argv[3:]
    return None


# --- the mission's side ---------------------------------------------------------------------


class LaunchedProcess:
    """A module forked by the launcher, with the part of :class:`subprocess.Popen`'s interface
    the supervisor uses (pid, poll, wait, terminate, kill)."""

    def __init__(self, launcher: Launcher, pid: int) -> None:
        self._launcher = launcher
        self.pid = pid

    @property
    def returncode(self) -> int | None:
        return self._launcher.exit_code(self.pid)

    def poll(self) -> int | None:
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._launcher.cv:
            while (code := self._launcher.exit_code(self.pid)) is None:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    raise subprocess.TimeoutExpired(f"module pid {self.pid}", timeout or 0)
                self._launcher.cv.wait(0.2 if left is None else min(left, 0.2))
        return code

    def _signal(self, sig: int) -> None:
        if self.returncode is None:  # never a pid the kernel may have given to another
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, sig)

    def terminate(self) -> None:
        self._signal(signal.SIGTERM)

    def kill(self) -> None:
        self._signal(signal.SIGKILL)


class Launcher:
    """The launcher process of one mission, started just before its modules (starting it
    earlier, beside the mission's own set-up, measured no faster). Thread-safe."""

    def __init__(self, log_file: Path) -> None:
        self._log = open(log_file, "w")  # noqa: SIM115 -- closed in close()
        self.proc = subprocess.Popen([sys.executable, "-m", "mission.runtime.launcher"],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=self._log, bufsize=0)
        self.cv = threading.Condition()
        self._pids: dict[int, int | str] = {}  # request id -> pid, or why it failed
        self._codes: dict[int, int] = {}
        self._mine: set[int] = set()
        self._next = 0
        self._reader = threading.Thread(target=self._read, name="launcher", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            msg = json.loads(line)
            with self.cv:
                if "exit" in msg:
                    self._codes[msg["exit"]] = msg["code"]
                else:
                    self._pids[msg["id"]] = msg.get("pid", msg.get("error", "?"))
                self.cv.notify_all()
        with self.cv:  # the launcher is gone
            self.cv.notify_all()

    def exit_code(self, pid: int) -> int | None:
        with self.cv:
            code = self._codes.get(pid)
            if code is None and self.proc.poll() is not None and not _exists(pid):
                # The launcher died before it could report (it reaps its modules); the
                # module is gone all the same.
                code = self._codes[pid] = -signal.SIGKILL
            return code

    def spawn(self, args: list[str], log_path: Path, append: bool) -> LaunchedProcess:
        """Fork the module of ``mission.runtime.modules`` arguments ``args``, logging to
        ``log_path``."""
        with self.cv:
            rid = self._next
            self._next += 1
            request = {"id": rid, "argv": args, "log": str(log_path), "append": append}
            try:
                assert self.proc.stdin is not None
                self.proc.stdin.write((json.dumps(request) + "\n").encode())
            except (BrokenPipeError, OSError) as exc:
                raise MissionFailed(f"the module launcher is gone ({exc}); its log is "
                                    f"{self._log.name}") from None
            deadline = time.monotonic() + SPAWN_TIMEOUT_S
            while rid not in self._pids:
                left = deadline - time.monotonic()
                if left <= 0 or self.proc.poll() is not None:
                    raise MissionFailed(
                        f"the module launcher did not start {args[0]} "
                        f"({'it exited' if self.proc.poll() is not None else 'timed out'}); "
                        f"its log is {self._log.name}")
                self.cv.wait(min(left, 0.2))
            got = self._pids.pop(rid)
        if isinstance(got, str):
            raise MissionFailed(f"the module launcher could not start {args[0]}: {got}")
        return LaunchedProcess(self, got)

    def close(self) -> None:
        """Close the launcher's stdin: it exits (its modules run on until they stop)."""
        try:
            if self.proc.stdin is not None:
                self.proc.stdin.close()
        except OSError:
            pass
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self._log.close()


def _exists(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


# --- the launcher's side --------------------------------------------------------------------


def _child(request: dict[str, Any], keep_closed: list[int]) -> None:
    """In the forked module: its own log as stdout and stderr, default signals, then the
    module's program as ``python -m mission.runtime.modules ARGS`` runs it. Never returns."""
    code = 1
    try:
        signal.set_wakeup_fd(-1)
        for sig in (signal.SIGCHLD, signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, signal.SIG_DFL)
        for fd in keep_closed:
            os.close(fd)
        flags = os.O_WRONLY | os.O_CREAT | (os.O_APPEND if request["append"] else os.O_TRUNC)
        out = os.open(request["log"], flags, 0o644)
        os.dup2(out, 1)
        os.dup2(out, 2)
        os.close(out)
        null = os.open(os.devnull, os.O_RDONLY)
        os.dup2(null, 0)
        os.close(null)
        argv = list(request["argv"])
        sys.argv = [sys.argv[0], *argv]
        from setproctitle import setproctitle
        setproctitle("rovergate " + " ".join(argv))  # what ps and pgrep show
        from mission.runtime.modules import main
        main(argv)
        code = 0
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        if isinstance(exc.code, str):
            print(exc.code, file=sys.stderr)
    except BaseException:  # noqa: BLE001 -- the module's traceback goes to its log
        traceback.print_exc()
    finally:
        try:
            sys.stdout.flush()
            sys.stderr.flush()
        finally:
            os._exit(code)


def serve() -> None:
    """The launcher's loop (see the module docstring)."""
    # Ctrl-C reaches every process of the terminal's group: the modules stop themselves and
    # the mission closes this pipe.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    import importlib
    for name in PRELOAD:
        importlib.import_module(name)
    from rovergate.graph import TOPICS
    from rovergate.messages import prepare
    prepare(set(TOPICS))
    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_w, False)
    signal.set_wakeup_fd(wake_w)
    signal.signal(signal.SIGCHLD, lambda *_: None)
    requests, replies = sys.stdin.buffer, os.dup(1)
    os.dup2(2, 1)  # a stray print goes to the log, not into the replies

    def reply(msg: dict[str, Any]) -> None:
        os.write(replies, (json.dumps(msg) + "\n").encode())

    pending = b""
    fd = requests.fileno()
    while True:
        ready, _, _ = select.select([fd, wake_r], [], [])
        if wake_r in ready:
            os.read(wake_r, 4096)
        while True:  # reap every module that exited
            try:
                pid, status = os.waitpid(-1, os.WNOHANG)
            except ChildProcessError:
                break
            if pid == 0:
                break
            reply({"exit": pid, "code": os.waitstatus_to_exitcode(status)})
        if fd in ready:
            chunk = os.read(fd, 65536)
            if not chunk:
                return  # the mission closed the pipe
            pending += chunk
            while b"\n" in pending:
                line, pending = pending.split(b"\n", 1)
                request = json.loads(line)
                sys.stdout.flush()
                sys.stderr.flush()
                try:
                    pid = os.fork()
                except OSError as exc:
                    reply({"id": request["id"], "error": str(exc)})
                    continue
                if pid == 0:
                    _child(request, [fd, replies, wake_r, wake_w])
                reply({"id": request["id"], "pid": pid})


if __name__ == "__main__":
    serve()
