"""The manual says what the code does: every ``rovergate`` command written in the README or a
docs page reads as the real command line reads it (so a page cannot name a flag that is not
there), the site builds strictly, the topic table is the generated one, every benchmark
command starts, and the README's first mission and first study run as written (with fewer
steps)."""

from __future__ import annotations

import contextlib
import io
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from rovergate import graph
from rovergate.errors import ConfigError

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
FENCE = re.compile(r"^```(bash|sh|console|shell)\n(.*?)^```", re.S | re.M)


def command_lines(text: str) -> list[str]:
    """The shell lines of a page's bash blocks, continuations joined, comments dropped."""
    out = []
    for block in FENCE.finditer(text):
        joined = block.group(2).replace("\\\n", " ")
        for line in joined.splitlines():
            line = line.strip().removeprefix("$ ")
            if line and not line.startswith("#"):
                out.append(line)
    return out


def rovergate_commands() -> list[tuple[str, list[str]]]:
    """Every ``rovergate ...`` invocation of every page: (page, argv after ``rovergate``)."""
    found = []
    for page in PAGES:
        for line in command_lines(page.read_text()):
            for part in re.split(r"\s(?:&&|\|\||\||;|&)\s|\s&$", line):
                words = shlex.split(part, comments=True)
                for i, w in enumerate(words):
                    if w.endswith("/rovergate") or w == "rovergate":
                        found.append((str(page.relative_to(ROOT)), words[i + 1:]))
                        break
    return found


COMMANDS = rovergate_commands()


def test_the_pages_write_rovergate_commands():
    pages = {page for page, _ in COMMANDS}
    assert {"README.md", "docs/running.md", "docs/study.md", "docs/operations.md"} <= pages
    assert len(COMMANDS) > 40, COMMANDS


@pytest.mark.parametrize("page,argv", COMMANDS,
                         ids=[f"{p}:{' '.join(a)[:60]}" for p, a in COMMANDS])
def test_every_command_in_the_docs_parses(page, argv):
    """A flag the command does not have, or a value it refuses, fails here with tyro's
    message. A file the page names as an example (``my_site.ply``, ``DIR/rover``) need not
    exist: a ConfigError naming a missing file passes."""
    from mission.cli import parse
    from mission.run import check_runnable
    from rovergate.config import MissionConfig
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            parsed = parse(argv)
        # A mission's names (condition, scene, start, planner) and ranges are checked as
        # `rovergate run` checks them before anything starts.
        cfg = parsed if isinstance(parsed, MissionConfig) else getattr(parsed, "config", None)
        if isinstance(cfg, MissionConfig):
            check_runnable(cfg)
    except SystemExit as e:  # tyro: an unknown flag or a bad value (or --help: 0)
        assert e.code == 0, f"{page}: `rovergate {shlex.join(argv)}` is refused:\n" \
                            f"{err.getvalue()[-2000:]}"
    except ConfigError as e:
        missing = [a for a in argv if ("/" in a or "." in a) and not (ROOT / a).exists()]
        assert missing and any(m in str(e) for m in missing), \
            f"{page}: `rovergate {shlex.join(argv)}`: {e}"


def test_a_wrong_flag_in_a_page_would_fail():
    from mission.cli import parse
    with pytest.raises(SystemExit) as e, contextlib.redirect_stderr(io.StringIO()):
        parse(["run", "--session.multicast-scouting"])
    assert e.value.code == 2


def test_architecture_topic_table_is_the_generated_one():
    page = (ROOT / "docs" / "architecture.md").read_text()
    m = re.search(r"<!-- topics:[^\n]*-->\n(.*?)\n<!-- /topics -->", page, re.S)
    assert m, "docs/architecture.md lost its topic table markers"
    assert m.group(1) == graph.topic_table(), \
        "docs/architecture.md's topic table is stale: paste `python -m rovergate.graph` " \
        "between the markers"


@pytest.mark.e2e
def test_docs_benchmark_commands_start_as_written():
    """Every benchmark program a page names starts (``--help``) with the project's
    interpreter, from the project root, as the page writes it."""
    commands = set()
    for page in PAGES:
        commands |= set(re.findall(r"`(\S*python) (benchmarks/\w+\.py)", page.read_text()))
    assert len(commands) >= 5, commands
    for interpreter, program in sorted(commands):
        assert interpreter == ".venv/bin/python", (interpreter, program)
        r = subprocess.run([sys.executable, program, "--help"], cwd=ROOT, capture_output=True,
                           text=True, timeout=120)
        assert r.returncode == 0 and "usage" in r.stdout.lower(), (program, r.stderr[-1500:])


def _readme_block(heading: str) -> list[list[str]]:
    text = (ROOT / "README.md").read_text()
    section = text.split(f"## {heading}\n", 1)[1].split("\n## ", 1)[0]
    return [shlex.split(line, comments=True) for line in command_lines(section)]


def _short(argv: list[str], tmp: Path, steps: int) -> list[str]:
    """The command with ``--steps`` set to ``steps`` and ``--out`` under ``tmp``."""
    out = list(argv)
    for flag, value in (("--steps", str(steps)), ("--out", str(tmp / "out"))):
        if flag in out:
            out[out.index(flag) + 1] = value
        else:
            out += [flag, value]
    return out


@pytest.mark.e2e
def test_readme_first_mission_runs_as_written(tmp_path):
    """The README's "A first mission of your own": the first mission command that is not
    --help, run as written but for 4 steps and its output place."""
    runs = [w for w in _readme_block("A first mission of your own")
            if w[1] == "run" and "--help" not in w]
    assert runs
    argv = _short(runs[0][1:], tmp_path, 4) + ["--no-record"]
    r = subprocess.run([sys.executable, "-m", "mission.cli", *argv], cwd=ROOT,
                       capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stderr[-3000:]
    assert (tmp_path / "out" / "metrics.json").is_file()


@pytest.mark.e2e
def test_readme_first_study_runs_as_written(tmp_path):
    """The README's "A first study", its first command, with 2 steps a run."""
    study = _readme_block("A first study")[0]
    assert study[1] == "study"
    argv = _short(study[1:], tmp_path, 2)
    r = subprocess.run([sys.executable, "-m", "mission.cli", *argv], cwd=ROOT,
                       capture_output=True, text=True, timeout=400)
    assert r.returncode == 0, r.stderr[-3000:]
    assert (tmp_path / "out" / "table1.md").is_file()
