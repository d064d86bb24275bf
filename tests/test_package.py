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
    assert name in dir(ts)


def test_an_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="has no attribute 'HeatFlowz'"):
        ts.HeatFlowz  # noqa: B018
    assert not hasattr(ts, "_private")
