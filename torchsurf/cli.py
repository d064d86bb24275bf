"""The ``torchsurf`` command: ``torchsurf run CONFIG [--set key=value ...] [--out DIR]`` and
``torchsurf list`` (docs/cli.md).

Exit codes: 0 done, 2 usage or config error (nothing computed), 1 the run itself failed.
"""

from __future__ import annotations

import argparse
import errno
import os
import signal
import sys
import tempfile
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

from ._signals import signals_held
from .config import ConfigError, builtin_folder, builtin_names

EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="torchsurf",
        description="PDEs on implicit surfaces: run the paper's experiments from config files.",
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    run = commands.add_parser("run", help="run an experiment config and write its pictures")
    run.add_argument("config", nargs="?", help="a config file, or the name of a shipped config "
                     "(see `torchsurf list`)")
    run.add_argument("--set", dest="overrides", action="extend", nargs="+", default=[],
                     metavar="KEY=VALUE", help="override settings, e.g. --set grid.size=96 "
                     "flow.time=0.002")
    run.add_argument("--out", default=None, help="output folder (default outputs/<name>)")
    run.add_argument("--quiet", action="store_true", help="print nothing but errors")
    run.add_argument("--no-progress", action="store_true", help="no progress bar")
    commands.add_parser("list", help="list the shipped configs and what each shows")
    parser.set_defaults(run_parser=run)
    return parser


def _description(name: str) -> str:
    from omegaconf import OmegaConf

    text = OmegaConf.load(builtin_folder() / f"{name}.yaml").get("description", "")
    return " ".join(str(text).split())


def list_configs() -> str:
    """One line per shipped config: its name and description."""
    names = builtin_names()
    width = max((len(n) for n in names), default=0)
    return "\n".join(f"{name:<{width}}  {_description(name)}" for name in names)


def _progress_wanted(disabled: bool) -> bool:
    if disabled or not sys.stderr.isatty():
        return False
    try:
        import tqdm  # noqa: F401
    except ImportError:
        return False
    return True


def _check_writable(folder: Path, files: Sequence[Path] = ()) -> list[Path]:
    """Create ``folder`` if needed and write and remove a file in it, before any computation;
    the ``files`` the run will write there must not be folders.

    Returns:
        The folders this created, deepest first (:func:`_remove_if_empty` takes them back).

    Raises:
        OSError: the folder cannot be created or written, or one of ``files`` is a folder.
    """
    for path in files:
        if path.is_dir():
            raise IsADirectoryError(errno.EISDIR, "a folder stands where the run writes its "
                                    "file", str(path))
    created = [parent for parent in (folder, *folder.parents) if not parent.exists()]
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError:
        _remove_if_empty(created)
        raise
    return created


def _remove_if_empty(folders: list[Path]) -> None:
    """Remove the ``folders`` (deepest first) that hold nothing: a failed run leaves no trace."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:
            return


def _take_config_from_overrides(args: argparse.Namespace) -> None:
    """``run --set a=1 CONFIG``: ``--set`` takes every word after it, the config name too. The
    one word without ``=`` in ``--set``'s list is the config when none came before it."""
    if args.config is not None:
        return
    names = [item for item in args.overrides if "=" not in item]
    if not names:
        args.run_parser.error("the following arguments are required: config")
    if len(names) > 1:
        args.run_parser.error(f"--set takes key=value words; {', '.join(map(repr, names))} are "
                              "not, and only one of them can be the config")
    args.config = names[0]
    args.overrides = [item for item in args.overrides if item != names[0]]


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line ``argv`` (default ``sys.argv[1:]``); returns the exit code."""
    try:
        args = _parser().parse_args(argv)
        if args.command == "run":
            _take_config_from_overrides(args)
    except SystemExit as stop:
        return int(stop.code or 0)
    if args.command == "list":
        try:
            print(list_configs(), flush=True)
        except BrokenPipeError:  # `torchsurf list | head`: the reader had what it wanted
            _silence_stdout()
        return EXIT_OK
    with warnings.catch_warnings():
        if args.quiet:  # "nothing but errors": the library's RuntimeWarnings too
            warnings.simplefilter("ignore")
        previous, warnings.formatwarning = warnings.formatwarning, _format_warning
        try:
            return _run(args, argv)
        finally:
            warnings.formatwarning = previous


def _format_warning(message: Warning | str, category: type[Warning], filename: str,
                    lineno: int, line: str | None = None) -> str:
    """A warning during a run as one line, ``torchsurf: <category>: <message>``: the library
    names the frame outside it, which from the command line is Python's own (``<frozen
    runpy>:88``), with its source line."""
    return f"torchsurf: {category.__name__}: {message}\n"


def _silence_stdout() -> None:
    """Point stdout at the null device, so that the interpreter's exit flush is quiet."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())


def _console_log() -> Callable[[str], None]:
    """``print``, until stdout fails (a closed pipe, ``| head -1``; a full disk): then nothing
    more, stdout silenced. Losing the log does not lose the run: a failed ``print`` inside the
    run had ended it as failed, with nothing written."""
    failed = False

    def log(message: str) -> None:
        nonlocal failed
        if failed:
            return
        try:
            print(message, flush=True)
        except OSError:
            failed = True
            _silence_stdout()

    return log


def _run(args: argparse.Namespace, argv: Sequence[str] | None) -> int:
    """``torchsurf run`` with the parsed ``args``; returns the exit code."""
    # trimesh guards its optional imports with `except BaseException`, which swallowed a
    # Ctrl-C given meanwhile (the run went on and replaced the outputs): taken once loaded
    with signals_held():
        from . import experiment

    if args.out is not None and not args.out.strip():
        print("torchsurf: --out must name a folder, got an empty string", file=sys.stderr)
        return EXIT_USAGE
    try:
        prepared = experiment.prepare(args.config, args.overrides)
    except ConfigError as error:
        print(f"torchsurf: config error: {error}", file=sys.stderr)
        return EXIT_USAGE
    try:  # VTK's import does not survive an interrupt: load it before any folder is made
        from .render import resolve_renderer

        with signals_held():
            resolve_renderer(prepared.experiment.render.renderer.name)
    except ImportError as error:
        print(f"torchsurf: {error}", file=sys.stderr)
        return EXIT_FAILED
    out = Path(args.out) if args.out else Path("outputs") / prepared.experiment.name
    try:
        created = _check_writable(out, experiment.output_paths(prepared.experiment.name, out))
    except OSError as error:
        print(f"torchsurf: cannot write to {str(out)!r} (--out): {error}", file=sys.stderr)
        return EXIT_USAGE
    log = (lambda message: None) if args.quiet else _console_log()
    try:
        given = sys.argv[1:] if argv is None else list(argv)
        result = experiment.run(prepared, out,
                                progress=_progress_wanted(args.no_progress or args.quiet), log=log,
                                command=["torchsurf", *given])
    except ImportError as error:
        _remove_if_empty(created)
        print(f"torchsurf: {error}", file=sys.stderr)
        return EXIT_FAILED
    except ConfigError as error:  # found once the surface is built (flow.time's equilibrium)
        _remove_if_empty(created)
        print(f"torchsurf: config error: {error}", file=sys.stderr)
        return EXIT_USAGE
    except (ValueError, FloatingPointError, RuntimeError, OSError, MemoryError) as error:
        _remove_if_empty(created)
        print(f"torchsurf: run failed: {type(error).__name__}: {error}", file=sys.stderr)
        return EXIT_FAILED
    except BaseException:  # Ctrl-C, SIGTERM: the folders this run made go too, if empty
        _remove_if_empty(created)
        raise
    times = ", ".join(f"{k} {v:.1f} s" for k, v in result.stages.items())
    log(f"stages: {times}")
    log(f"wrote {result.picture} and {result.record}")
    return EXIT_OK


def _exit_on_terminate(signum: int, frame: object) -> None:
    raise SystemExit(128 + signum)


def entry_point() -> None:
    """The console script: ``sys.exit(main())``. ``SIGTERM`` (``kill``, a job scheduler's
    stop) exits like Ctrl-C does, through the cleanup that removes half-written files: by
    default it ended the process on the spot and left an empty temporary picture behind.
    Ctrl-C exits with 130 and one line, once that cleanup has run (not a traceback)."""
    signal.signal(signal.SIGTERM, _exit_on_terminate)
    try:
        code = main()
    except KeyboardInterrupt:
        print("torchsurf: interrupted", file=sys.stderr)
        code = 128 + signal.SIGINT
    sys.exit(code)
