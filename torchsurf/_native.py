"""Small C kernels compiled once per machine and loaded with ctypes.

A :class:`NativeLibrary` holds the C source of a few functions. On first use it is compiled
with the C compiler that ``torch.compile`` also needs (``$CC``, else ``cc``), half a second
to 2.3 s a library, into a cache folder: ``$TORCHSURF_CACHE_DIR``, else
``$XDG_CACHE_HOME/torchsurf``, else ``~/.cache/torchsurf``. The file's name holds a hash of
the source, the flags, the compiler's command and version and the CPU's feature flags
(``-march=native``); it is written aside and renamed into place, so a concurrent process
finds it whole or not at all, and a cached file shorter than its headers say is compiled
again. Without a compiler, or with ``TORCHSURF_NATIVE=never``, :meth:`NativeLibrary.load`
returns ``None`` and the callers take their other paths (with a ``RuntimeWarning`` per library unless
``never``); :meth:`NativeLibrary.unavailable_reason` says why.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shlex
import subprocess
import tempfile
import threading
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from torch.autograd import forward_ad

from ._stack import caller_stacklevel

NATIVE_MODES = ("auto", "never")
"""Values of the environment variable ``TORCHSURF_NATIVE``."""

FLAGS = (("-O3", "-march=native", "-mprefer-vector-width=256", "-shared", "-fPIC"),
         ("-O3", "-shared", "-fPIC"))
"""Tried in turn. 256-bit vectors: a row of 8 float32 values fills one (with 512-bit ones gcc
leaves the octant kernel's row loop scalar); the second set for compilers or CPUs that refuse
the first (``-mprefer-vector-width`` is gcc's, for x86)."""


def native_mode() -> str:
    """``TORCHSURF_NATIVE``, checked: ``"auto"`` (the default) or ``"never"``."""
    value = os.environ.get("TORCHSURF_NATIVE", "auto").strip().lower() or "auto"
    if value not in NATIVE_MODES:
        raise ValueError(f"TORCHSURF_NATIVE must be one of {NATIVE_MODES}, got {value!r}")
    return value


def cache_dir() -> Path:
    """Where compiled kernels are kept (module docstring)."""
    if os.environ.get("TORCHSURF_CACHE_DIR"):
        return Path(os.environ["TORCHSURF_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "torchsurf"


def _machine_key() -> str:
    """What ``-march=native`` compiles for: the CPU's feature flags."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith(("flags", "Features")):
                return line
    except OSError:
        pass
    import platform
    return platform.processor() or platform.machine()


def _compiler_command() -> list[str]:
    """``$CC`` (else ``cc``) as a command and its arguments, as make reads it; a ``$CC`` that
    does not parse raises ``RuntimeError`` (the library's reason for not loading)."""
    text = os.environ.get("CC") or "cc"
    try:
        return shlex.split(text) or ["cc"]
    except ValueError as error:
        raise RuntimeError(f"$CC={text!r} does not parse as a command: {error}") from error


class NativeLibrary:
    """C functions compiled on first use and kept for the process.

    Args:
        name: the shared library's file name stem.
        source: returns the C source (called once, when the library is first needed).
        functions: each exported function's name and ``ctypes`` argument types (it returns
            nothing).
        flags: added to the first set of :data:`FLAGS` (the second, plain set stays plain).
    """

    def __init__(self, name: str, source: Callable[[], str],
                 functions: dict[str, Sequence[type]], flags: Sequence[str] = ()) -> None:
        self.name = name
        self._flag_sets = ((*FLAGS[0], *flags), *FLAGS[1:])
        self._source = source
        self._functions = dict(functions)
        self._lock = threading.Lock()
        self._state: dict[str, object] = {}

    def load(self) -> ctypes.CDLL | None:
        """The compiled library, compiled on first use; ``None`` where it cannot be."""
        with self._lock:
            if "library" not in self._state:
                try:
                    if native_mode() == "never":
                        raise RuntimeError("TORCHSURF_NATIVE=never")
                    self._state["library"] = self._compile(_compiler_command())
                    self._state["reason"] = None
                except (OSError, RuntimeError, subprocess.SubprocessError) as error:
                    detail = getattr(error, "stderr", None) or error
                    self._state["library"] = None
                    self._state["reason"] = f"{type(error).__name__}: {str(detail).strip()[:500]}"
                    if native_mode() != "never":
                        warnings.warn(
                            f"torchsurf's C kernel {self.name!r} is unavailable, its callers "
                            f"take their other, slower paths: {self._state['reason']} (cache "
                            f"folder {cache_dir()}, compiler $CC, else cc; "
                            "TORCHSURF_NATIVE=never silences this)",
                            RuntimeWarning, stacklevel=caller_stacklevel())
            return self._state["library"]  # type: ignore[return-value]

    def unavailable_reason(self) -> str | None:
        """Why :meth:`load` returns ``None`` (no compiler, ``TORCHSURF_NATIVE=never``, a
        ``TORCHSURF_NATIVE`` that is neither mode), or ``None``."""
        try:
            self.load()
        except ValueError as error:
            return str(error)
        return self._state["reason"]  # type: ignore[return-value]

    def forget(self) -> None:
        """Load again on the next call (after the environment changed)."""
        with self._lock:
            self._state = {}

    def _compile(self, compiler: list[str]) -> ctypes.CDLL:
        """The library built by ``compiler`` (a command and its arguments, as make's ``$CC``:
        ``"ccache gcc"``, ``"gcc -std=c11"``)."""
        version = subprocess.run([*compiler, "--version"], capture_output=True, text=True,
                                 check=True, timeout=60).stdout
        source = self._source()
        for rebuild in (False, True):
            for attempt, flags in enumerate(self._flag_sets):
                try:
                    built = self._built(source, compiler, version, flags, rebuild)
                    break
                except subprocess.CalledProcessError:
                    if attempt == len(self._flag_sets) - 1:
                        raise
            try:
                return self._bound(ctypes.CDLL(str(built)))
            except (OSError, AttributeError) as error:
                # a cached file that is not this library (truncated, overwritten, another
                # build's): compiled again once, in its place
                if rebuild:
                    raise RuntimeError(f"{built} does not load as {self.name}: {error}") from error
        raise AssertionError("unreachable")

    def _bound(self, loaded: ctypes.CDLL) -> ctypes.CDLL:
        """``loaded`` with each exported function's argument types set (``AttributeError``
        for one it lacks)."""
        for name, argtypes in self._functions.items():
            function = getattr(loaded, name)
            function.restype = None
            function.argtypes = list(argtypes)
        return loaded

    def _built(self, source: str, compiler: list[str], version: str, flags: tuple[str, ...],
               rebuild: bool = False) -> Path:
        """The shared library for these flags, compiled unless the cache holds it (or
        ``rebuild``)."""
        key = hashlib.sha256(
            "\0".join((source, *compiler, *flags, version, _machine_key())).encode())
        folder = cache_dir()
        library = folder / f"{self.name}_{key.hexdigest()[:20]}.so"
        if rebuild or not library.exists() or not _whole(library):
            folder.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryDirectory(dir=folder) as work:
                c_file = Path(work) / f"{self.name}.c"
                c_file.write_text(source)
                built = Path(work) / library.name
                subprocess.run([*compiler, *flags, "-o", str(built), str(c_file)],
                               capture_output=True, text=True, check=True, timeout=120)
                os.replace(built, library)  # whole or not at all, also for a concurrent process
        return library


def _whole(library: Path) -> bool:
    """Whether an ELF file reaches as far as its headers say: a cached library cut short (an
    interrupted copy, a full disk) killed the process with SIGBUS when loaded. Files of other
    formats are taken as they are."""
    try:
        with library.open("rb") as file:
            header = file.read(64)
            size = os.fstat(file.fileno()).st_size
    except OSError:
        return False
    if len(header) < 64 or header[:4] != b"\x7fELF" or header[4] != 2:  # 64-bit ELF only
        return True
    order = "little" if header[5] == 1 else "big"
    section_table = int.from_bytes(header[0x28:0x30], order)
    entry_size = int.from_bytes(header[0x3A:0x3C], order)
    entries = int.from_bytes(header[0x3C:0x3E], order)
    return section_table + entry_size * entries <= size


def carries_tangents(*tensors: torch.Tensor) -> bool:
    """Whether any of ``tensors`` carries what a kernel reading its raw memory would drop: a
    forward-mode tangent (:mod:`torch.autograd.forward_ad`) or a ``torch.func`` transform's
    wrapper (``jvp``, ``vmap``, ``grad``). The kernels' callers then take their differentiable
    paths, as for a tensor that requires grad. ``False`` while ``torch.compile`` traces (the
    callers trace their own paths there)."""
    if torch.compiler.is_compiling():
        return False
    wrapped = getattr(torch._C._functorch, "is_functorch_wrapped_tensor", None)
    for tensor in tensors:
        if wrapped is not None and wrapped(tensor):
            return True
        if forward_ad.unpack_dual(tensor).tangent is not None:
            return True
    return False


def in_parts(count: int, least: int) -> int:
    """The parts :func:`in_threads` splits ``count`` items into (at least ``least`` each)."""
    return max(1, min(torch.get_num_threads(), count // max(least, 1)))


def in_threads(run: Callable[[int, int], None], count: int, least: int) -> None:
    """``run(first, stop)`` over ``[0, count)`` in up to :func:`torch.get_num_threads` parts of
    at least ``least`` items, on threads started for the call (ctypes releases the GIL; no pool
    to outlive a ``fork``)."""
    parts = in_parts(count, least)
    bounds = [count * i // parts for i in range(parts + 1)]
    workers = [threading.Thread(target=run, args=(bounds[i], bounds[i + 1]))
               for i in range(1, parts)]
    for worker in workers:
        worker.start()
    try:
        run(bounds[0], bounds[1])
    finally:
        for worker in workers:
            worker.join()
