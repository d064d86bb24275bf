"""Writing a benchmark's figures into a markdown file (docs/benchmarks.md), and naming the machine
they ran on; shared by the scripts."""

from __future__ import annotations

import argparse
import fcntl
import hashlib
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

NEW_FILE = ("# torchsurf benchmarks\n\nFigures measured by the scripts in `benchmarks/`; each "
            "section says how to reproduce it.\n")


def write_section(path: Path, name: str, heading: str, body: str,
                  after: str | None = None) -> None:
    """Write or replace the section ``name`` (between ``<!-- BEGIN name ... -->`` and
    ``<!-- END name -->``) in ``path``: ``heading``, then ``body``.

    Only a section exactly as a run wrote it is replaced: its BEGIN marker carries a checksum of
    what was written. A section edited by hand since (or written before the checksums) is kept
    whole, its markers renamed ``name, kept``, and the new section goes just before it, so
    that notes written beside the figures are never lost. A new section goes after the
    section ``after`` when ``path`` has it, else at the end.

    Writers hold a lock on ``path`` + ``.lock`` while they read and write, and write a
    temporary file of their own that is renamed into place: the file is never left half
    written and concurrent runs do not lose each other's sections.

    Raises:
        ValueError: ``path`` has a BEGIN marker of ``name`` without its END (or the reverse).
    """
    content = f"{heading}\n\n{body}\n"
    section = f"<!-- BEGIN {name} {_checksum(content)} -->\n{content}<!-- END {name} -->\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path.with_name(path.name + ".lock"), "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        text = path.read_text() if path.exists() else NEW_FILE
        _replace_atomically(path, _with_section(text, name, section, after))


def _with_section(text: str, name: str, section: str, after: str | None) -> str:
    begin = re.compile(rf"<!-- BEGIN {re.escape(name)}(?: ([0-9a-f]{{16}}))? -->\n")
    end = f"<!-- END {name} -->\n"
    found = begin.search(text)
    has_end = end in (text if found is None else text[found.end():])
    if (found is not None) != has_end:
        raise ValueError(f"a BEGIN or END marker of section {name!r} is missing its pair; "
                         "fix the file by hand before writing the section again")
    if found is not None:
        stop = text.index(end, found.end())
        content = text[found.end():stop]
        rest = text[stop + len(end):]
        if found.group(1) == _checksum(content):
            return text[:found.start()] + section + rest
        kept = (f"<!-- BEGIN {name}, kept -->\n{content}<!-- END {name}, kept -->\n")
        return text[:found.start()] + section + "\n" + kept + rest
    follows = None if after is None else f"<!-- END {after} -->\n"
    if follows is not None and follows in text:
        head, rest = text.split(follows, 1)
        return head + follows + "\n" + section + _after(rest)
    return text.rstrip("\n") + "\n\n" + section


def _checksum(content: str) -> str:
    return hashlib.sha256(content.encode()).hexdigest()[:16]


def _replace_atomically(path: Path, text: str) -> None:
    """``path`` holds ``text``, with its former permissions (or the umask's)."""
    mode = path.stat().st_mode & 0o777 if path.exists() else 0o666 & ~_umask()
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.",
                                         suffix=".tmp")
    try:
        with os.fdopen(handle, "w") as file:
            file.write(text)
        os.chmod(temporary, mode)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


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


def run_context() -> str:
    """One line that says where and how a figure was measured: the CPU, its count, torch's
    threads and version, the allocator setting (``GLIBC_TUNABLES``), the load average and the
    time (UTC)."""
    import datetime
    import os

    import torch

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    when = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    return (f"{cpu_model()}, {os.cpu_count()} CPUs, {torch.get_num_threads()} torch thread(s), "
            f"torch {torch.__version__}, allocator: "
            f"{os.environ.get('GLIBC_TUNABLES', 'glibc default')}, load average {load:.1f}, {when}")


def alternated(roots: dict[str, Path], count: int,
               run: Callable[[Path], dict[str, float]]) -> dict[str, list[dict[str, float]]]:
    """``count`` runs of ``run(root)`` per checkout of ``roots`` (name -> root), the checkouts
    taking turns, so that the machine's drift falls on each alike."""
    runs: dict[str, list[dict[str, float]]] = {name: [] for name in roots}
    for _ in range(count):
        for name, root in roots.items():
            runs[name].append(run(root))
    return runs


def figures(runs: list[dict[str, float]], key: str, digits: int) -> str:
    """The runs' ``key`` figures, ``" / "`` between them."""
    return " / ".join(f"{run[key]:.{digits}f}" for run in runs)


def checksum_offsets(runs: list[dict[str, float]], reference: float) -> str:
    """How far each run's ``"checksum"`` lies from ``reference``, relative."""
    return " / ".join(f"{abs(run['checksum'] - reference) / max(abs(reference), 1e-300):.1e}"
                      for run in runs)


def add_alternation_arguments(parser: argparse.ArgumentParser, runs: int) -> None:
    """``--runs`` (fresh processes per checkout, default ``runs``), ``--baseline`` (the root
    of another checkout to alternate with), ``--output`` and the children's ``--worker``."""
    parser.add_argument("--runs", type=int, default=runs, help="fresh processes per checkout")
    parser.add_argument("--baseline", type=Path, default=None,
                        help="root of another checkout to alternate with")
    parser.add_argument("--output", type=Path, default=None)
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)


def checkouts(root: Path, baseline: Path | None) -> dict[str, Path]:
    """This checkout's root as ``"this"``, and ``baseline`` as ``"baseline"`` if given."""
    return {"this": root} if baseline is None else {"this": root, "baseline": baseline}


def worker_result(script: str, root: Path, arguments: list[str],
                  environment: dict[str, str] | None = None) -> dict[str, float]:
    """What a benchmark's ``script`` run with ``--worker`` and ``arguments`` prints last (a JSON
    object), in a fresh process importing torchsurf from ``root``, its working directory the
    benchmarks folder, with ``environment`` added to this process's."""
    variables = {**os.environ, **(environment or {}), "PYTHONPATH": str(root)}
    command = [sys.executable, script, "--worker", *arguments]
    finished = subprocess.run(command, env=variables, capture_output=True, text=True,
                              cwd=Path(script).resolve().parent)
    if finished.returncode != 0:  # the worker's own error, not only its exit status
        raise RuntimeError(f"{' '.join(command)} (torchsurf from {root}) failed with exit status "
                           f"{finished.returncode}:\n{finished.stderr.strip()[-4000:]}")
    return json.loads(finished.stdout.strip().splitlines()[-1])
