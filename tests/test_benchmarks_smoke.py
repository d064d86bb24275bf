"""Smoke test of benchmarks/bench_laplace_beltrami.py: its numpy reference is the library's stencil."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import torchsurf as ts

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def load_benchmark(name: str):  # noqa: ANN201
    """The script ``benchmarks/<name>.py`` as a module (its folder on the path, as when run)."""
    if str(BENCHMARKS) not in sys.path:
        sys.path.insert(0, str(BENCHMARKS))
    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses resolve annotations through sys.modules
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("bench_laplace_beltrami")


def test_numpy_reference_is_the_conservative_scheme(bench):
    grid = ts.Grid.cube(17, 1.5)
    phi = ts.sdf.sphere(grid, dtype=torch.float64)
    surface = ts.ImplicitSurface(phi, grid)
    generator = torch.Generator().manual_seed(1)
    u = torch.rand((1, 1, 17, 17, 17), generator=generator, dtype=torch.float64)

    expected = ts.laplace_beltrami(u, surface, scheme="conservative", path="slicing")
    reference = bench.AppendixB(phi[0, 0].numpy(), grid.spacing, dtype=np.float64)
    actual = reference(u[0, 0].numpy()).copy()

    assert actual.dtype == np.float64
    np.testing.assert_allclose(actual, expected[0, 0].numpy(), rtol=0, atol=1e-10)
    # the reference's normals are the surface's
    normal, weight = bench.numpy_normals(phi[0, 0].numpy(), grid.spacing)
    np.testing.assert_allclose(normal, surface.normal[0].numpy(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(weight, surface.weight[0, 0].numpy(), rtol=0, atol=1e-12)


def test_numpy_reference_float32_buffers_are_reused(bench):
    grid = ts.Grid.cube(9, 1.5)
    phi = ts.sdf.sphere(grid)
    reference = bench.AppendixB(phi[0, 0].numpy(), grid.spacing)
    u = np.random.default_rng(0).random((9, 9, 9), dtype=np.float32)
    first = reference(u).copy()
    second = reference(u)
    assert second.dtype == np.float32
    np.testing.assert_array_equal(first, second)




def test_bricks_benchmark_time_to_solution_and_report():
    module = load_benchmark("bench_bricks")
    rows, (best, peer) = module.solution([41], target=0.05)
    assert rows[0]["error"] < 0.05 and best is rows[0]
    assert peer.error <= 0.05 or not peer.reached
    args = module.argparse.Namespace(mesh="bunny_closed.obj", solution_method="rkc")
    text = module.markdown(args, 20.0, None, None, (rows, (best, peer)))
    assert "| 41 |" in text and "Mesh peer" in text
    # at the dense case's spacing, on a box wide enough for bricks: Euler on the 25^3 spacing
    rows, _ = module.solution([25], target=0.05, method="euler")
    assert rows[0]["error"] < 1e-3 and rows[0]["steps"] > 1




def test_bricks_benchmark_peak_part_runs_a_users_run_in_a_child_process():
    module = load_benchmark("bench_bricks")
    mesh = module.MESHES / "bunny_closed.obj"
    if not mesh.exists():
        pytest.skip("shared meshes not present")
    text = module.peak(mesh, 40)
    assert "A user's run alone** (40³ `bunny_closed.obj`" in text and "GB**." in text


def test_bricks_benchmark_times_the_c_kernel_and_reports_it():
    module = load_benchmark("bench_bricks")
    grid = ts.Grid.cube(33, 1.5)
    surface = module.bricks.from_dense(ts.sdf.sphere(grid, 1.0), grid)
    band = surface.band_mask()
    u = torch.randn(len(surface.layout), 1, 8, 8, 8)
    every, on_band, planes, _ = module._native_times(u, surface, band)
    if module._native.library() is not None:
        assert every > 0 and on_band > 0 and planes > 0
        assert torch.equal(module._on_band_planes(surface, band)(u),
                           module._on_band(u, surface, band))
    ratioed = {"resolution": 33, "dense_ms": 2.0, "brick_ms": 1.0, "ratios": [0.5],
               "native_ms": 0.3, "native_ratios": [0.15], "planes_ms": 0.45, "stored": 10,
               "band": 5, "dense": 100}
    args = module.argparse.Namespace(mesh="bunny_closed.obj")
    text = module.markdown(args, 20.0, None, ratioed, None)
    assert "The C kernel on the band only" in text and "time ratio 0.150" in text
    assert "0.5 ms, 1.50x" in text


@pytest.fixture(scope="module")
def learned_bench():
    module = load_benchmark("bench_learned_diffusion")
    return module


def test_learned_diffusion_bench_runs_one_iteration(learned_bench):
    # compiled=True leaves the backend's thresholds alone (the eager setting is per process)
    for method in learned_bench.METHODS:
        run = learned_bench.Run(**learned_bench.single(method, 1.0, 17, 1, 2, compiled=True))
        assert run.method == method and run.first > 0 and run.steady > 0
        assert run.live_mb >= 0 and run.peak_mb >= 0
        assert run.world == pytest.approx(1.0 * (3.0 / 16) ** 2)


def test_learned_diffusion_bench_summary_reads_the_ratios(learned_bench):
    Run = learned_bench.Run
    runs = [Run("learned", 0.044, 1e-4, 1.0, 1.0, 110.0, 100.0),
            Run("learned", 4.4, 1e-2, 5.0, 5.0, 150.0, 110.0),
            Run("heatflow", 0.044, 1e-4, 1.0, 1.0, 100.0, 100.0),
            Run("heatflow", 4.4, 1e-2, 30.0, 30.0, 900.0, 800.0)]
    lines = learned_bench.summary(runs, 0.044, 4.4)
    assert "live memory x1.10" in lines[0] and "time x5.00" in lines[0]
    assert lines[0].endswith("meets the targets")
    assert "live memory x8.00" in lines[1] and lines[1].endswith("misses the targets")
    assert "| learned | 4.4 | 0.01 | 5.00 | 5.00 | 110 | 150 |" in learned_bench.table(runs)


def test_bricks_benchmark_batch_runs_and_reports(tmp_path, monkeypatch):
    import trimesh

    monkeypatch.setattr(ts.backend, "COMPILE_MIN_VOXELS", ts.backend.COMPILE_MIN_VOXELS)
    monkeypatch.setattr(ts.backend, "COMPILE_PAYBACK_SECONDS", ts.backend.COMPILE_PAYBACK_SECONDS)
    module = load_benchmark("bench_bricks")
    meshes = [tmp_path / "sphere.obj", tmp_path / "box.obj"]
    trimesh.creation.icosphere(2, radius=5.0).export(meshes[0])
    trimesh.creation.box((0.1, 0.2, 0.3)).export(meshes[1])
    runs = [module.batch_run(meshes, [24, 20], 1.0, which, tmp_path / f"{which}.pt")
            for which in (None, 0, 1)]
    assert runs[0]["bricks"] == runs[1]["bricks"] + runs[2]["bricks"]
    result = {"batch": runs[0], "alone": runs[1:], "differences": [1e-7, 2e-7],
              "excess": [-0.1, -0.2], "names": ["sphere", "box"], "resolutions": [24, 20],
              "cells": 1.0}
    text = module.batch_markdown(result)
    assert "| sphere alone, 24^3 |" in text and "sum of the 2 alone" in text




def test_compile_bench_measures_every_item_and_tabulates():
    module = load_benchmark("bench_compile")
    for item in (*module.OPERATORS, *module.LAYERS):
        call, data, _ = module.build(item, "slicing", 9, 2, torch.float32)
        with torch.no_grad():
            assert call(data).shape[0] == 2, item
    cold = module.measure("lb_octant", "slicing", "cold", 9, 2, torch.float32, 1, 0.0)
    assert cold.first_forward_s > 0 and cold.steady_train_ms > 0 and not cold.error
    text = module.table([(cold, None)])
    assert text.splitlines()[-1].startswith("| lb_octant | slicing |")


def test_operators_bench_alternates_with_its_baseline_and_tabulates():
    module = load_benchmark("bench_operators")
    calls = []
    first, second = module.alternated_times(lambda: calls.append(1), lambda: calls.append(2), 3)
    assert calls == [1, 2, 1, 2, 1, 2] and len(first) == len(second) == 3
    rows = module.bench_size(9, 1, "slicing", log=lambda line: None, only=["colour"])
    assert [row.name for row in rows] == ["laplace_beltrami octant", "colour rate (3 ch)"]
    assert all(row.ratio > 0 and row.forward_ms > 0 for row in rows)
    text = module.markdown({9: rows}, {"torch": 20.0}, "slicing", ["--sizes", "9"])
    assert text.splitlines()[-1].startswith("| colour rate (3 ch) | 3 |")


def test_sections_are_replaced_in_place_or_added_after_their_neighbour(tmp_path):
    report = load_benchmark("_report")
    path = tmp_path / "sub" / "benchmarks.md"
    report.write_section(path, "a", "## A", "first")
    report.write_section(path, "c", "## C", "third")
    report.write_section(path, "b", "## B", "second", after="a")
    report.write_section(path, "a", "## A", "first again")
    text = path.read_text()
    assert text.startswith(report.NEW_FILE)
    assert text.index("first again") < text.index("second") < text.index("third")
    assert "first\n" not in text and text.count("<!-- BEGIN a ") == 1
    assert sorted(p.name for p in path.parent.iterdir()) == ["benchmarks.md", "benchmarks.md.lock"]


def test_notes_written_into_a_section_by_hand_are_kept(tmp_path):
    """A rerun replaced everything between the markers: 125 lines of notes in the bricks
    section would have gone with the command the doc quotes."""
    report = load_benchmark("_report")
    path = tmp_path / "benchmarks.md"
    report.write_section(path, "a", "## A", "| run | 1 |")
    report.write_section(path, "b", "## B", "other")
    path.write_text(path.read_text().replace("| run | 1 |", "| run | 1 |\n\nA note by hand."))
    report.write_section(path, "a", "## A", "| run | 2 |")
    text = path.read_text()
    assert text.index("| run | 2 |") < text.index("| run | 1 |") < text.index("A note by hand.")
    assert text.count("<!-- BEGIN a, kept -->") == 1 and "other" in text
    report.write_section(path, "a", "## A", "| run | 3 |")  # the unedited run is replaced
    text = path.read_text()
    assert "| run | 2 |" not in text and text.index("| run | 3 |") < text.index("A note by hand.")
    # a legacy section with no checksum is kept the same way
    path.write_text(path.read_text() + "<!-- BEGIN c -->\n## C\n\nold notes\n<!-- END c -->\n")
    report.write_section(path, "c", "## C", "new")
    assert "old notes" in path.read_text() and "new" in path.read_text()


def test_concurrent_writers_keep_every_section_and_a_lone_marker_is_refused(tmp_path):
    import threading

    report = load_benchmark("_report")
    path = tmp_path / "benchmarks.md"
    threads = [threading.Thread(target=report.write_section,
                                args=(path, f"s{i}", f"## S{i}", f"body {i}")) for i in range(12)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    text = path.read_text()
    assert all(f"body {i}\n" in text for i in range(12))
    path.write_text(text + "<!-- BEGIN orphan -->\nhalf\n")
    with pytest.raises(ValueError, match="'orphan' is missing its pair"):
        report.write_section(path, "orphan", "## O", "x")
    assert path.read_text().endswith("half\n")


def test_a_failing_worker_names_its_own_error(tmp_path):
    """A worker's failure had shown only "returned non-zero exit status 1"; the worker's error
    (a mesh not found, say) is now part of the message."""
    report = load_benchmark("_report")
    script = tmp_path / "bench_failing.py"
    script.write_text("raise FileNotFoundError('mesh: no mesh file at nowhere.obj')\n")
    with pytest.raises(RuntimeError, match="(?s)exit status 1.*no mesh file at nowhere.obj"):
        report.worker_result(str(script), tmp_path, [])
    script.write_text("print('{\"first\": 1.5}')\n")
    assert report.worker_result(str(script), tmp_path, []) == {"first": 1.5}


def test_narrow_band_bench_runs_its_four_rows_and_the_bound_holds():
    """benchmarks/bench_narrow_band.py at 12 cells per radius on both surfaces: the default RKC's
    steps last at most 12 / rho, the baseline's are the former count."""
    module = load_benchmark("bench_narrow_band")
    for layout in ("dense", "bricks"):
        rows = module.run(12, layout)
        assert len(rows) == 4
        cells = [row.split(" | ") for row in rows]
        assert cells[0][2] == "rkc (default)" and float(cells[0][4]) <= 12.0 + 1e-9
        assert cells[1][2].startswith("rkc, former bound") and int(cells[1][3]) >= 16
        assert all(float(c[5]) < 5e-2 for c in cells), rows


def test_narrow_band_sweep_and_phis_tabulate_what_docs_band_md_reads():
    """``--sweep``: at every period RKC in short steps errs as Heun does (the period, not the
    integrator, sets the error); ``--phis``: a multiple of the distance gives the distance's
    numbers, on the 5-cell band."""
    module = load_benchmark("bench_narrow_band")
    rows = module.sweep(10, "dense", periods=(4, 12))
    assert len(rows) == 2
    for row in rows:
        heun, short = (float(c) for c in row.strip("| ").split(" | ")[3:5])
        assert abs(heun - short) < 0.1 * abs(heun) + 2e-4, row
    rows = module.phis(10)
    assert len(rows) == 2 * len(module.PHIS)
    distance, multiple = rows[0].split(" | "), rows[2].split(" | ")
    assert distance[2] == multiple[2] == "5" and distance[5:] == multiple[5:], rows


def test_first_call_benchmark_runs_a_flow_and_writes_its_section(tmp_path, capsys):
    """``bench_first_call.py`` on a tiny grid, this checkout against itself: one fresh process
    a run, both calls timed, the results equal, the section written."""
    module = load_benchmark("bench_first_call")
    if not (module.MESH_DIR / "spot.obj").is_file():
        pytest.skip(f"test mesh spot.obj not found in {module.MESH_DIR}")
    output = tmp_path / "benchmarks.md"
    module.main(["--meshes", "spot", "--resolution", "20", "--flows", "heat", "--runs", "1",
                 "--baseline", str(module.ROOT), "--output", str(output)])
    text = output.read_text()
    assert "| spot | 20 | heat | this |" in text and "| spot | 20 | heat | baseline |" in text
    assert "first call, this ÷ baseline" in text and "| 0.0e+00 |" in text


def test_nonlinear_benchmark_runs_each_case_and_writes_its_section(tmp_path):
    """``bench_nonlinear.py`` on a tiny grid, this checkout against itself: the analytic case
    in a fresh process each, the section written (the mesh cases take 10-15 s a process:
    left to a person's run)."""
    module = load_benchmark("bench_nonlinear")
    output = tmp_path / "benchmarks.md"
    cases = ["harmonic"]
    module.main(["--cases", *cases, "--resolution", "20", "--runs", "1", "--baseline",
                 str(module.ROOT), "--output", str(output)])
    text = output.read_text()
    for case in cases:
        assert f"| {case} | 20 | this |" in text and f"| {case} | 20 | baseline |" in text
    assert text.count("this ÷ baseline") == len(cases) and "| 0.0e+00 |" in text
