"""Smoke test of benchmarks/bench_heat_flow.py: the mesh peer solves the same problem, and the
summary reads the issue's ratios off the rows correctly."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

BENCHMARK = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_heat_flow.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_heat_flow", BENCHMARK)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def test_mesh_operators_of_this_file_match_libigl(bench):
    vertices, faces = bench.icosphere(2)
    laplacian, mass = bench.mesh_operators(vertices, faces, "igl")
    own_laplacian, own_mass = bench.mesh_operators(vertices, faces, "numpy")
    np.testing.assert_allclose(own_laplacian.toarray(), laplacian.toarray(), atol=1e-12)
    np.testing.assert_allclose(own_mass, mass, rtol=1e-12)


def test_mesh_peer_decays_the_harmonic(bench):
    """Icosphere(4), backward Euler: within a few per cent of ``exp(-6 t)``; coarser is worse."""
    fine, coarse = bench.mesh_error(4, 64), bench.mesh_error(2, 64)
    assert fine < 5e-3 < coarse


def test_summary_takes_the_fastest_run_within_the_target(bench):
    rows = [
        bench.Row(65, "euler (h^2/6)", 100, 0.2, 2e-3),
        bench.Row(81, "euler (h^2/6)", 150, 0.4, 9e-4),
        bench.Row(97, "euler (h^2/6)", 200, 1.0, 6e-4),
        bench.Row(129, bench.REFERENCE_NAME, 300, 15.0, 1.3e-3),
        bench.Row(193, bench.REFERENCE_NAME, 600, 120.0, 8e-4),
        bench.Row(81, "mesh peer icosphere(5), 45 BE steps", 10242, 0.1, 9e-4),
        bench.Row(65, "rkc (default)", 100, 0.5, 2e-3),
        bench.Row(81, "rkc (default)", 150, 0.6, 8e-4),
        bench.Row(81, "rkc (3-cell band)", 150, 0.3, 9e-4),  # faster, but not the default
    ]
    text = "\n".join(bench.time_to_accuracy(rows, 1e-3))
    assert "| euler | 81 | 0.400 |" in text
    assert "(target >= 20): 400.00" in text
    assert "(target <= 0.1): 3.00" in text
    assert "default (rkc) ÷ mesh peer: 6.00" in text
