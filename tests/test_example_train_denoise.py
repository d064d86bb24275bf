"""Smoke test of examples/train_denoise.py: a ``--quick`` run writes its table, pictures and
weights, with finite numbers, and leaves torchsurf's compile thresholds as they were."""

from __future__ import annotations

import csv
import importlib.util
import math
import sys
from pathlib import Path

import pytest

import torchsurf as ts

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "train_denoise.py"


@pytest.fixture(scope="module")
def example():
    spec = importlib.util.spec_from_file_location("train_denoise", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses resolve annotations through sys.modules
    spec.loader.exec_module(module)
    return module


def test_quick_run_writes_table_and_pictures(example, tmp_path):
    thresholds = ts.backend.COMPILE_MIN_VOXELS, ts.backend.COMPILE_PAYBACK_SECONDS
    scores = example.main(["--quick", "--output", str(tmp_path / "out")])
    output = tmp_path / "out"

    assert (ts.backend.COMPILE_MIN_VOXELS, ts.backend.COMPILE_PAYBACK_SECONDS) == thresholds
    with open(output / "results.csv", newline="") as stream:
        rows = list(csv.DictReader(stream))
    cells = {(row["method"], row["set"], row["kind"]) for row in rows}
    assert cells == {(m, s, k) for m in example.METHODS for s in example.SETS
                     for k in ts.datasets.KINDS}
    assert len(rows) == len(cells)
    for row in rows:
        value = float(row["psnr_db"])
        assert math.isfinite(value) and 5.0 < value < 80.0, row
        assert value == pytest.approx(scores[row["method"], row["set"], row["kind"]], abs=1e-4)

    markdown = (output / "results.md").read_text()
    assert "| learned - heat |" in markdown and markdown.count("\n| ") == 2 + len(example.METHODS)
    for kind in ts.datasets.KINDS:
        picture = (output / f"heldout_{kind}.png").read_bytes()
        assert picture.startswith(b"\x89PNG\r\n\x1a\n") and len(picture) > 1000
    assert (output / "denoiser.pt").stat().st_size > 0
    assert not list(output.glob(".*")), "a temporary file was left behind"


def test_outputs_are_staged_and_a_failure_leaves_the_former_ones(example, tmp_path, monkeypatch):
    """A failure on the second picture left the new table, weights and first picture beside
    the former second picture: every output is written aside and renamed once all are."""
    former = {name: b"former" for name in ("results.md", "results.csv", "denoiser.pt",
                                           "heldout_smooth.png", "heldout_piecewise_constant.png")}
    for name, data in former.items():
        (tmp_path / name).write_bytes(data)
    drawn = example.render.render_panels
    calls = []

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise RuntimeError("the second picture failed")
        return drawn(*args, **kwargs)

    monkeypatch.setattr(example.render, "render_panels", failing)
    with pytest.raises(RuntimeError, match="second picture"):
        example.main(["--quick", "--output", str(tmp_path)])
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == former


@pytest.mark.parametrize(("argv", "named"), [
    (["--resolution", "8"], "--resolution"),
    (["--iterations", "0"], "--iterations"),
    (["--noise", "-1"], "--noise"),
    (["--threads", "0"], "--threads"),  # torch's own error, naming no option
    (["--quick", "--iterations", "0"], "--iterations"),  # --quick made it 2 without a word
    (["--meshes", "spot.obj", "--heldout-mesh", "spot.obj"], "--heldout-mesh"),
    (["--mesh-dir", "a", "--meshes", "../b/x.obj", "--heldout-mesh", "../b/x.obj"],
     "--heldout-mesh"),
    # these ran, failing later in the library without naming the option
    (["--lr", "inf"], "--lr"),
    (["--noise", "1e300"], "--noise"),
    (["--noise", "1e-50"], "--noise"),  # 0 in float32: the noisy set was the clean one
    (["--frequency", "nan"], "--frequency"),
    (["--seed", "-5"], "--seed"),
    (["--seed", str(2**32)], "--seed"),
    # an abbreviation was taken by argparse, then overridden by --quick
    (["--quick", "--res", "32"], "--res"),
    # a traceback at the first mesh's loading, after the options had passed
    (["--mesh-dir", "/nonexistent", "--meshes", "spot.obj"], "--meshes 'spot.obj'"),
    (["--heldout-mesh", "/nonexistent/spot.obj"], "--heldout-mesh"),
])
def test_bad_arguments_are_named(example, capsys, argv, named):
    with pytest.raises(SystemExit):
        example.parse(argv)
    assert named in capsys.readouterr().err


def test_an_output_that_cannot_be_a_folder_is_refused_before_the_run(example, capsys,
                                                                    tmp_path):
    """A file in --output's path had the run fail at its very end, after minutes of work."""
    (tmp_path / "results.md").write_text("")
    for output in ("results.md", "results.md/out"):
        with pytest.raises(SystemExit):
            example.parse(["--output", str(tmp_path / output)])
        assert "is not a folder" in capsys.readouterr().err
    assert example.parse(["--output", str(tmp_path / "new" / "folder")])  # made at the end
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results.md"]  # the trial removed


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux's /proc")
def test_an_output_on_a_pseudo_file_system_is_refused_before_the_run(example, capsys):
    """Permission bits let root write into /proc; the run failed at its end, making the
    folder."""
    with pytest.raises(SystemExit):
        example.parse(["--output", "/proc/torchsurf-results"])
    assert "--output /proc/torchsurf-results: cannot make a folder in /proc" in capsys.readouterr().err


def test_relative_mesh_without_folder_is_refused(example):
    with pytest.raises(FileNotFoundError, match="--meshes 'spot.obj'"):
        example.mesh_paths(["spot.obj"], None)


def test_the_same_mesh_by_another_name_is_refused_and_another_file_taken(example, capsys,
                                                                        tmp_path):
    """The held-out mesh was compared with --meshes by file name only: a spot.obj of
    another folder was refused, the same file reached by another path was not."""
    for folder in ("a", "b"):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "spot.obj").write_text("")
    assert example.parse(["--mesh-dir", str(tmp_path), "--meshes", "a/spot.obj",
                          "--heldout-mesh", "b/spot.obj"])
    with pytest.raises(SystemExit):
        example.parse(["--mesh-dir", "m", "--meshes", "spot.obj", "--heldout-mesh",
                       "./sub/../spot.obj"])
    assert "--heldout-mesh" in capsys.readouterr().err


def test_too_many_cells_name_the_option(example, tmp_path):
    with pytest.raises(SystemExit, match="--cells 100000 is too many at --resolution 24"):
        example.main(["--quick", "--cells", "100000", "--output", str(tmp_path)])


def test_options_given_beside_quick_stand(example):
    args = example.parse(["--quick", "--resolution", "32", "--channels=3"])
    assert (args.resolution, args.channels, args.iterations) == (32, 3, 2)
