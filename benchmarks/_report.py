"""Writing a benchmark's figures into a markdown file (docs/benchmarks.md), and naming the machine
they ran on; shared by the scripts."""

from __future__ import annotations

import platform
from pathlib import Path

NEW_FILE = ("# torchsurf benchmarks\n\nFigures measured by the scripts in `benchmarks/`; each "
            "section says how to reproduce it.\n")


def write_section(path: Path, name: str, heading: str, body: str,
                  after: str | None = None) -> None:
    """Write or replace the section ``name`` (between ``<!-- BEGIN name -->`` and
    ``<!-- END name -->``) in ``path``: ``heading``, then ``body``.

    A new section goes after the section ``after`` when ``path`` has it, else at the end. The
    file is written whole to a temporary file and renamed, so it is never left half written.
    """
    begin, end = f"<!-- BEGIN {name} -->", f"<!-- END {name} -->"
    section = f"{begin}\n{heading}\n\n{body}\n{end}\n"
    text = path.read_text() if path.exists() else NEW_FILE
    follows = None if after is None else f"<!-- END {after} -->"
    if begin in text and end in text:
        head, rest = text.split(begin, 1)
        text = head + section + _after(rest.split(end, 1)[1])
    elif follows is not None and follows in text:
        head, rest = text.split(follows, 1)
        text = head + follows + "\n\n" + section + _after(rest)
    else:
        text = text.rstrip("\n") + "\n\n" + section
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_suffix(".tmp")
    temporary.write_text(text)
    temporary.replace(path)


def _after(rest: str) -> str:
    """What follows a section: one blank line, then the rest of the file."""
    rest = rest.lstrip("\n")
    return "\n" + rest if rest else ""


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``), or the platform's processor string."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()
