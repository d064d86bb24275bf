"""The package's names: loaded on first use, every one of ``__all__`` there."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

import torchsurf as ts


def test_importing_the_package_and_the_command_loads_no_heavy_library():
    """``import torchsurf`` (and the command's module) must not load torch or trimesh: the
    command holds interrupts while it loads them (tests/test_cli.py)."""
    script = ("import sys, torchsurf, torchsurf.cli; "
              "print(sorted(m for m in ('torch', 'trimesh', 'numpy') if m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=120, env={**os.environ, "OMP_NUM_THREADS": "1"}, check=True)
    assert done.stdout.strip() == "[]"


@pytest.mark.parametrize("name", ts.__all__)
def test_every_public_name_resolves(name):
    value = getattr(ts, name)
    assert value is getattr(ts, name)


def test_every_public_submodule_is_an_attribute_after_import_alone():
    """``ts.signals``, ``ts.render``, ``ts.grid`` ... (documented as the package's modules)
    were attributes only once another import had loaded them: loaded on first use now. In a
    fresh process, where nothing else has loaded them."""
    from pathlib import Path

    folder = Path(ts.__file__).parent
    names = sorted(path.stem for path in folder.iterdir()
                   if not path.name.startswith("_") and (path.suffix == ".py" or (
                       path.is_dir() and (path / "__init__.py").exists())))
    assert {"signals", "render", "grid", "sampling", "surface", "curvature"} <= set(names)
    script = ("import importlib, torchsurf; names = " + repr(names) + "; "
              "print([n for n in names if not hasattr(torchsurf, n)])")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"}, check=True)
    assert done.stdout.strip() == "[]", done.stdout


def test_an_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="has no attribute 'HeatFlowz'"):
        ts.HeatFlowz  # noqa: B018
    assert not hasattr(ts, "_private")


@pytest.mark.parametrize("name", ["sdf", "mesh", "signals", "datasets", "render", "exact",
                                  "sampling", "surface", "grid", "shape_batch", "stencils",
                                  "backend", "curvature", "flows", "operators", "nn", "bricks"])
def test_every_public_module_states_its_names(name):
    """Without ``__all__`` a star import and an IDE offered the modules' imports as their own
    (``torchsurf.sdf.check_positive``, ``torchsurf.signals.HeatFlow``)."""
    import importlib

    module = importlib.import_module(f"torchsurf.{name}")
    assert module.__all__ and all(hasattr(module, item) for item in module.__all__)
    namespace: dict = {}
    exec(f"from torchsurf.{name} import *", namespace)  # noqa: S102
    assert "check_positive" not in namespace and "HeatFlow" not in namespace or name == "flows"


def test_names_that_are_no_module_are_attribute_errors():
    """A dotted name raised ModuleNotFoundError (``hasattr`` raised), ``flows.heat`` was taken
    and kept under a dotted name, and the configs' data folder loaded as a namespace package."""
    for name in ("nothing.here", "flows.heat", "configs", "__main__"):
        assert not hasattr(ts, name), name
    assert {"signals", "render", "grid", "curvature"} <= set(dir(ts))
