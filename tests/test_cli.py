"""The ``torchsurf`` command: every shipped config runs at a tiny size and draws a picture;
bad configs are refused with the key's path before any work; exit codes 0, 1, 2."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from torchsurf import cli, config

pytest.importorskip("matplotlib")
from matplotlib import image as mpimg  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
MESH_DIR = Path(
    os.environ.get("TORCHSURF_MESH_DIR", REPO / "../shared/data/meshes")
)
WIDTH, HEIGHT = 64, 48

TINY = ["grid.size=24", f"render.width={WIDTH}", f"render.height={HEIGHT}"]
"""Settings of every tiny run; the stiff flows also get a shorter time below."""

SHORTER = {
    "total_variation": ["flow.time=0.0005"],
    "harmonic": ["flow.time=0.0003"],
    "color": ["flow.time=0.0003"],
    "reaction_diffusion": ["flow.time=40"],
    "visualization": ["flow.time=4", "field.smoothing=1"],
}


def _load(name: str) -> config.Experiment:
    return config.load(name)[0]


BUILTIN = [n for n in config.builtin_names() if _load(n).surface.shape is not config.Shape.mesh]
MESHES = [n for n in config.builtin_names() if _load(n).surface.shape is config.Shape.mesh]


def _tiny_args(name: str) -> list[str]:
    return TINY + SHORTER.get(_load(name).flow.kind.name, [])


def _check_picture(path: Path, panels: int) -> None:
    picture = mpimg.imread(path)
    assert picture.shape[:2] == (HEIGHT, panels * WIDTH)
    for index in range(panels):
        panel = picture[:, index * WIDTH:(index + 1) * WIDTH, :3]
        assert panel.std() > 0.02, f"panel {index} of {path.name} is uniform"


def test_every_config_has_a_builtin_variant_and_a_description():
    assert len(BUILTIN) >= 8
    for name in config.builtin_names():
        assert _load(name).name == name
        assert _load(name).description
    kinds = {_load(n).flow.kind for n in BUILTIN}
    assert kinds == set(config.FlowKind)


@pytest.mark.parametrize("name", BUILTIN)
def test_builtin_config_runs_at_a_tiny_size(name, tmp_path, capsys):
    code = cli.main(["run", name, "--set", *_tiny_args(name), "--out", str(tmp_path)])
    assert code == cli.EXIT_OK, capsys.readouterr().err
    experiment = _load(name)
    _check_picture(tmp_path / f"{name}.png", len(experiment.render.panels))
    record = json.loads((tmp_path / f"{name}.json").read_text())
    assert record["config"]["grid"]["size"] == 24
    assert set(record["stages_seconds"]) == {"surface", "signal", "flow", "render"}
    assert record["physical"]["time"] > 0
    assert None not in _leaves(record["flow"]), record["flow"]
    assert record["versions"]["torch"]
    # the arguments given, not the process's sys.argv (pytest's here)
    assert record["command"][:3] == ["torchsurf", "run", name]
    printed = capsys.readouterr().out
    assert "physical time" in printed
    assert not list(tmp_path.glob(".*")), "a temporary file was left behind"


def test_a_direction_field_s_error_is_measured_on_the_directions_sign_free():
    """The record's RMS for a field was taken of |T|'s components at the vertices (the
    picture's): a field with one component negated, 47 degrees off on average, scored 0."""
    from torchsurf.experiment import _sign_free_rms

    generator = torch.Generator().manual_seed(0)
    clean = torch.nn.functional.normalize(torch.randn(1, 3, 4, 5, 6, generator=generator), dim=1)
    near = torch.ones(1, 1, 4, 5, 6, dtype=torch.bool)
    assert _sign_free_rms(clean, clean, near) == 0.0
    assert _sign_free_rms(-clean, clean, near) == 0.0  # a line field's T and -T are one
    mirrored = clean * torch.tensor([1.0, -1.0, 1.0]).view(1, 3, 1, 1, 1)
    expected = torch.minimum(2 * clean[:, 1].abs(), 2 * (clean[:, 0].square()
                             + clean[:, 2].square()).sqrt())
    assert _sign_free_rms(mirrored, clean, near) == pytest.approx(
        float((expected.square().mean() / 3).sqrt()), rel=1e-6)
    assert _sign_free_rms(mirrored, clean, near) > 0.2
    near[..., :3] = False  # only the nodes of near count
    assert _sign_free_rms(torch.where(near, clean, -mirrored), clean, near) == 0.0


@pytest.mark.slow
@pytest.mark.parametrize("name", MESHES)
def test_mesh_config_runs_at_a_tiny_size(name, tmp_path, monkeypatch):
    mesh = _load(name).surface.mesh
    if not (MESH_DIR / mesh).is_file():
        pytest.skip(f"test mesh {mesh} not found in {MESH_DIR} (set TORCHSURF_MESH_DIR)")
    monkeypatch.setenv(config.MESH_DIR_VARIABLE, str(MESH_DIR))
    code = cli.main(["run", name, "--set", *_tiny_args(name), "--out", str(tmp_path), "--quiet"])
    assert code == cli.EXIT_OK
    _check_picture(tmp_path / f"{name}.png", len(_load(name).render.panels))


def _leaves(data: object) -> list[object]:
    if isinstance(data, dict):
        return [leaf for value in data.values() for leaf in _leaves(value)]
    return [data]


@pytest.mark.parametrize(("overrides", "method"), [
    ([], "rkc"), (["flow.method=euler"], "euler"), (["flow.steps=5"], "rkc"),
])
def test_record_holds_the_flow_settings_the_run_used(overrides, method, tmp_path, monkeypatch):
    """``flow`` records what ran: the defaults a config leaves null, and the steps the flow
    planned (once: heat runs the image's channels together); ``config`` keeps the request."""
    from torchsurf.flows import base

    planned = []
    plan_steps = base.plan_steps

    def spy(*args, **kwargs):
        planned.append(plan_steps(*args, **kwargs))
        return planned[-1]

    monkeypatch.setattr(base, "plan_steps", spy)
    code = cli.main(["run", "heat_sphere", "--set", *TINY, *overrides, "--out", str(tmp_path),
                     "--quiet"])
    assert code == cli.EXIT_OK
    record = json.loads((tmp_path / "heat_sphere.json").read_text())
    steps = planned[-1].count
    assert len(planned) == 1
    assert record["flow"] == {"kind": "heat", "time": 0.0005, "time_unit": "diagonal",
                              "method": method, "steps": steps}
    requested = record["config"]["flow"]
    assert requested["method"] == ("euler" if "flow.method=euler" in overrides else None)
    assert requested["steps"] == (5 if "flow.steps=5" in overrides else None)
    assert requested["time_unit"] is None


def test_mesh_path_resolves_against_the_config_folder_then_the_mesh_dir(tmp_path, monkeypatch):
    folder = tmp_path / "meshes"
    folder.mkdir()
    trimesh.creation.icosphere(subdivisions=2).export(folder / "ball.obj")
    here = tmp_path / "here.yaml"
    here.write_text("name: ball\nsurface: {shape: mesh, mesh: meshes/ball.obj}\n"
                    "flow: {kind: heat, time: 0.0005}\n")
    code = cli.main(["run", str(here), "--set", *TINY, "--out", str(tmp_path / "out"),
                     "--quiet"])
    assert code == cli.EXIT_OK
    _check_picture(tmp_path / "out" / "ball.png", 2)

    elsewhere = tmp_path / "configs"
    elsewhere.mkdir()
    there = elsewhere / "there.yaml"
    there.write_text("name: ball\nsurface: {shape: mesh, mesh: ball.obj}\n")
    monkeypatch.delenv(config.MESH_DIR_VARIABLE, raising=False)
    with pytest.raises(config.ConfigError, match="surface.mesh"):
        config.resolve_mesh("ball.obj", elsewhere)
    monkeypatch.setenv(config.MESH_DIR_VARIABLE, str(folder))
    assert config.resolve_mesh("ball.obj", elsewhere) == folder / "ball.obj"
    # a relative mesh folder: the record's path had been relative to where the run started
    monkeypatch.chdir(elsewhere)
    monkeypatch.setenv(config.MESH_DIR_VARIABLE, "../meshes")
    assert config.resolve_mesh("ball.obj", elsewhere) == folder / "ball.obj"
    # a link to a file without an extension (a hub cache's blob) is named by the link
    blob = tmp_path / "blob"
    blob.write_bytes((folder / "ball.obj").read_bytes())
    (tmp_path / "linked.obj").symlink_to(blob)
    assert config.resolve_mesh(str(tmp_path / "linked.obj"), elsewhere) == tmp_path / "linked.obj"
    # ".." after a linked mesh folder: folded as text, it named another file than the one found
    (tmp_path / "store" / "meshes").mkdir(parents=True)
    (tmp_path / "store" / "extra").mkdir()
    (tmp_path / "store" / "extra" / "x.obj").write_bytes((folder / "ball.obj").read_bytes())
    (tmp_path / "linked").symlink_to(tmp_path / "store" / "meshes")
    monkeypatch.setenv(config.MESH_DIR_VARIABLE, str(tmp_path / "linked"))
    found = config.resolve_mesh("../extra/x.obj", elsewhere)
    assert found.is_file() and found.samefile(tmp_path / "store" / "extra" / "x.obj")
    # a folder was "not found"
    with pytest.raises(config.ConfigError, match="is a folder"):
        config.resolve_mesh(".", folder)


@pytest.mark.parametrize(
    ("overrides", "key"),
    [
        (["flow.foo=1"], "flow.foo"),
        (["colour=red"], "colour"),
        (["flow.kind=nope"], "flow.kind"),
        (["grid.size=abc"], "grid.size"),
        (["grid.size=4"], "grid.size"),
        (["flow.time=-1"], "flow.time"),
        (["flow.p=1.5"], "flow.p"),
        (["flow.kind=harmonic"], "signal.kind"),
        (["surface.params.radiuz=2"], "surface.params.radiuz"),
        (["surface.shape=mesh"], "surface.mesh"),
        (["surface.shape=mesh", "surface.mesh=no_such.obj"], "surface.mesh"),
        (["render.panels=[input,after]"], "render.panels[1]"),
        (["signal.image=no_such.png", "signal.kind=image"], "signal.image"),
        (["flow.time_unit=turk"], "flow.time_unit"),
        (["flowtime"], "--set"),
        (["signal.grain=0", "signal.kind=noise", "signal.image=null", "signal.projection=null"],
         "signal.grain"),
        (["signal.grain=2"], "signal.grain"),
        (["signal.kind=checkerboard"], "signal.image"),
        (["signal.kind=noise", "signal.image=null", "signal.projection=planar"],
         "signal.projection"),
        (["render.renderer=povray"], "render.renderer"),
        (["render.colormap=nosuchmap"], "render.colormap"),
        (["render.elevation=nan"], "render.elevation"),
        (["render.elevation=95"], "render.elevation"),
        (["render.azimuth=inf"], "render.azimuth"),
        (["grid.layout=sparse"], "grid.layout"),
        (["grid.layout=bricks", "grid.size=24"], "grid.margin"),
        (["flow.method=bogus"], "flow.method"),
        (["flow.method=scipy_solver"], "flow.method"),  # ran 500 s at 24^3, no cap
        (["flow.kind=total_variation", "flow.method=chebyshev"], "flow.method"),
        (["surface.params.radius=-1"], "surface.params"),
        (["name=../escaped"], "name"),
        (["name=a/b"], "name"),
        (["name=.hidden"], "name"),
        (["grid.size=24", "grid=3"], "grid"),
        (["signal.seed=-5"], "signal.seed"),
        (["signal.seed=99999999999999999999"], "signal.seed"),
        (["signal.noise=inf"], "signal.noise"),
        (["signal.grain=1e300", "signal.kind=noise", "signal.image=null", "signal.projection=null"],
         "signal.grain"),
        (["signal.tiles=1e300", "signal.kind=checkerboard", "signal.image=null",
          "signal.projection=null"], "signal.tiles"),
        (["signal.tiles=1e-300", "signal.kind=checkerboard", "signal.image=null",
          "signal.projection=null"], "signal.tiles"),
        (["threads=100000"], "threads"),
        (["signal.kind=noise", "signal.image=null", "signal.projection=null", "signal.noise=0.2"],
         "signal.noise"),
        (["field.kind=principal_max"], "field"),
        (["flow.method=chebyshev", "flow.steps=5"], "flow.steps"),
        (["flow.method=dopri5", "flow.steps=3"], "flow.steps"),
        (["flow.steps='5'"], "flow.steps"),
        (["grid.size='24'"], "grid.size"),
        (["signal.seed='12'"], "signal.seed"),
        (["name=" + "a" * 201], "name"),
        # a list where a mapping is expected, or the reverse: omegaconf's TypeError escaped
        (["surface.params=[1,2]"], "surface.params"),
        (["render.panels={a:1}"], "render.panels"),
        # refused only once the flow was called, after the surface was built (exit 1)
        (["flow.kind=total_variation", "flow.method=implicit"], "flow.method"),
        (["flow.kind=perona_malik", "flow.method=crank_nicolson"], "flow.method"),
        (["flow.steps=99999999999999999999"], "flow.steps"),
        # the sphere's poles touched the faces and the picture showed it cut flat (exit 0)
        (["grid.size=32", "grid.margin=0"], "grid.margin"),
        (["grid.size=32", "grid.margin=0.02"], "grid.margin"),
        # passed with a cell to spare, then the surface warned its operators wrong at the faces
        (["grid.size=16"], "grid.margin"),
        (["signal.gray=1"], "signal.gray"),  # taken as true
        # YAML 1.1 numbers in other bases or forms ran another number (032 as 26 nodes)
        (["grid.size=032"], "grid.size"),
        (["render.height=0x40"], "render.height"),
        (["render.width=1_00"], "render.width"),
        (["flow.time=1_000.5"], "flow.time"),
        (["flow.time=5_0e-5"], "flow.time"),  # text to PyYAML, a number to omegaconf
        (["surface.params={radius: 01}"], "surface.params.radius"),
        # a physical time float32 cannot hold failed after the surface was built (exit 1)
        (["flow.time=1e-300"], "flow.time"),
        (["flow.time=1e300"], "flow.time"),
        # a picture wider than off-screen VTK draws was written black (exit 0)
        (["render.panels=[input,output,output,output,output]", "render.width=3300"],
         "render.width"),
        # the CPU generator keeps 32 bits of a seed: 2**32 drew the noise of seed 0 (exit 0)
        (["signal.seed=4294967296"], "signal.seed"),
        # overflowed float32 into NaN once the surface was built (exit 1)
        (["signal.noise=1e300"], "signal.noise"),
        # interpolations half-worked: "not found" through --set, environment values recorded
        (["render.height=${render.width}"], "render.height"),
        (["description=${oc.env:HOME}"], "description"),
    ],
)
def test_bad_settings_are_refused_with_their_key(overrides, key, tmp_path, capsys):
    code = cli.main(["run", "heat_sphere", "--set", *overrides, "--out", str(tmp_path / "out")])
    assert code == cli.EXIT_USAGE
    error = capsys.readouterr().err
    assert f"config error: {key}:" in error
    assert not (tmp_path / "out").exists(), "work was done before the config was refused"


def test_interpolations_in_a_file_are_refused_with_their_key(tmp_path, capsys):
    written = tmp_path / "interpolated.yaml"
    written.write_text("name: x\nflow: {kind: heat}\nrender:\n  width: 64\n"
                       "  height: ${render.width}\n")
    assert cli.main(["run", str(written)]) == cli.EXIT_USAGE
    assert "config error: render.height: interpolations are not supported" in capsys.readouterr().err


def test_a_large_isotropic_weight_is_named_beside_the_time(tmp_path):
    """flowvis_trefoil with flow.isotropic=1e6 was refused as "flow.time: ... likely unit
    error", the time being the shipped one."""
    from torchsurf import experiment

    prepared = experiment.prepare("flowvis_trefoil", [*TINY, "flow.isotropic=1e6"])
    with pytest.raises(config.ConfigError, match="flow.time: .*flow.isotropic = 1e\\+06"):
        experiment.run(prepared, tmp_path, log=lambda message: None)


def test_bad_config_files_are_refused(tmp_path, capsys):
    unknown = tmp_path / "unknown.yaml"
    unknown.write_text("name: x\nflow:\n  kind: heat\n  tyme: 1\n")
    assert cli.main(["run", str(unknown)]) == cli.EXIT_USAGE
    assert "flow.tyme" in capsys.readouterr().err
    unnamed = tmp_path / "unnamed.yaml"
    unnamed.write_text("flow: {kind: heat}\n")
    assert cli.main(["run", str(unnamed)]) == cli.EXIT_USAGE
    assert "name" in capsys.readouterr().err
    assert cli.main(["run", "no_such_config"]) == cli.EXIT_USAGE
    assert "heat_sphere" in capsys.readouterr().err


def test_an_image_file_that_cannot_serve_is_refused_before_any_work(tmp_path, capsys):
    """A gray image for the colour flow and a file that is no image failed mid-run (exit 1),
    after the surface was built, naming no setting."""
    from PIL import Image

    gray = tmp_path / "gray.png"
    Image.fromarray(np.arange(64, dtype=np.uint8).reshape(8, 8) * 4, mode="L").save(gray)
    broken = tmp_path / "broken.png"
    broken.write_text("not an image")
    for name, path in (("color_sphere", gray), ("heat_sphere", broken)):
        code = cli.main(["run", name, "--set", "signal.kind=image", f"signal.image={path}",
                         "--out", str(tmp_path / "out")])
        assert code == cli.EXIT_USAGE
        assert "config error: signal.image:" in capsys.readouterr().err
        assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("override", ["flow.time=nan", "grid.margin=inf", "flow.time=-inf"])
def test_a_non_finite_number_is_refused_as_such(override, tmp_path, capsys):
    """YAML reads nan and inf unquoted as strings: they were refused as "a string (remove the
    quotes)", though none were typed."""
    code = cli.main(["run", "heat_sphere", "--set", override, "--out", str(tmp_path / "out")])
    assert code == cli.EXIT_USAGE
    error = capsys.readouterr().err
    assert f"config error: {override.split('=')[0]}: must be a finite number" in error
    assert "quotes" not in error


@pytest.mark.parametrize(("override", "typed"), [
    ("grid.size=048", "leading zero"), ("grid.size='48'", "in quotes")])
def test_a_number_yaml_reads_as_text_is_refused_naming_why(override, typed, tmp_path, capsys):
    """``grid.size=048`` (no quotes typed) was told to "remove the quotes"."""
    code = cli.main(["run", "heat_sphere", "--set", override, "--out", str(tmp_path / "out")])
    assert code == cli.EXIT_USAGE
    error = capsys.readouterr().err
    assert f"config error: {override.split('=')[0]}: must be a number, got the string" in error
    assert typed in error


def test_a_mesh_file_that_cannot_be_read_is_refused_before_any_work(tmp_path, capsys):
    """A file that is no mesh failed mid-run (exit 1, "run failed"), naming no setting."""
    for name, text in (("broken.obj", "not a mesh\n"), ("notes.md", "# no mesh\n")):
        path = tmp_path / name
        path.write_text(text)
        code = cli.main(["run", "heat_sphere", "--set", "surface.shape=mesh",
                         f"surface.mesh={path}", "--out", str(tmp_path / "out")])
        assert code == cli.EXIT_USAGE
        assert "config error: surface.mesh:" in capsys.readouterr().err
        assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("radius", ["1e-20", "1e300"])
def test_a_shape_beyond_float32_grids_is_refused_naming_its_parameters(tmp_path, capsys, radius):
    """A radius of 1e-20 failed in the flow ("no finite positive spectral bound"), 1e300 in
    the distances, both exit 1 naming no setting."""
    code = cli.main(["run", "heat_sphere", "--set", f"surface.params.radius={radius}",
                     "--out", str(tmp_path / "out")])
    assert code == cli.EXIT_USAGE
    assert "config error: surface.params: the sphere spans" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_a_bad_section_in_the_file_is_named_not_a_valid_override(tmp_path, capsys):
    """omegaconf names no key for a value given for a whole section: it was blamed on the
    first --set, valid or not, or on nothing."""
    broken = tmp_path / "broken.yaml"
    broken.write_text("name: a\ngrid: 3\n")
    for overrides in ([], ["--set", "flow.time=0.001"]):
        assert cli.main(["run", str(broken), *overrides]) == cli.EXIT_USAGE
        assert "config error: grid:" in capsys.readouterr().err
    for text, key in (("surface: {shape: sphere, params: [1, 2]}", "surface.params"),
                      ("render: {panels: {a: 1}}", "render.panels")):
        broken.write_text(f"name: a\n{text}\n")
        assert cli.main(["run", str(broken)]) == cli.EXIT_USAGE
        assert f"config error: {key}: a list given where a mapping" in capsys.readouterr().err


def test_the_coarse_grid_of_a_field_smoothing_needs_the_bricks_margin_too(tmp_path, capsys):
    """The margin was checked at grid.size only: the run built its surface, then failed
    (exit 1) on the coarser grid the field's smoothing builds the shape on again."""
    code = cli.main(["run", "flowvis_trefoil", "--set", "grid.layout=bricks", "grid.size=64",
                     "grid.margin=0.12", "field.smoothing=32", "field.smoothing_grid=16",
                     "--out", str(tmp_path / "out")])
    assert code == cli.EXIT_USAGE
    error = capsys.readouterr().err
    assert "config error: grid.margin: 0.12 leaves 1.45 cells around the shape on the 16^3 grid" \
        in error
    assert not (tmp_path / "out").exists()


def test_a_signal_setting_another_kind_reads_is_refused_and_null_unsets_it(tmp_path, capsys):
    """heat_sphere's file sets signal.image and signal.projection, read by images only."""
    code = cli.main(["run", "heat_sphere", "--set", *TINY, "signal.kind=checkerboard",
                     "--out", str(tmp_path)])
    assert code == cli.EXIT_USAGE
    error = capsys.readouterr().err
    assert "signal.image: not a setting of signal.kind=checkerboard (its settings: tiles)" in error
    assert "--set signal.image=null unsets it" in error
    code = cli.main(["run", "heat_sphere", "--set", *TINY, "signal.kind=checkerboard",
                     "signal.image=null", "signal.projection=null", "--out", str(tmp_path),
                     "--quiet"])
    assert code == cli.EXIT_OK
    record = json.loads((tmp_path / "heat_sphere.json").read_text())
    assert record["config"]["signal"]["tiles"] is None  # left to its default, 8


def test_a_mapping_given_whole_replaces_the_files_and_a_dotted_key_changes_one_entry():
    """flowvis_trefoil's file sets surface.params {tube_radius: 0.2, scale: 0.4}: switching
    the shape needed params cleared, and surface.params={} merged into them."""
    experiment, _ = config.load("flowvis_trefoil", ["surface.shape=torus", "surface.params={}"])
    assert experiment.surface.params == {}
    experiment, _ = config.load("flowvis_trefoil", ["surface.params={tube_radius: 0.15}"])
    assert experiment.surface.params == {"tube_radius": 0.15}
    experiment, _ = config.load("flowvis_trefoil", ["surface.params.tube_radius=0.15"])
    assert experiment.surface.params == {"tube_radius": 0.15, "scale": 0.4}
    experiment, _ = config.load("flowvis_trefoil", ["field={kind: axis}"])
    assert experiment.field.kind.name == "axis" and experiment.field.smoothing == 2.0


@pytest.mark.parametrize("text", ["name: 010", "name: yes", "name: x\ndescription: 3"])
def test_text_that_yaml_reads_as_a_number_or_a_boolean_is_refused_in_a_file(text, tmp_path, capsys):
    """``name: 010`` wrote ``8.png`` and ``name: yes`` ``True.png``: quote it."""
    path = tmp_path / "typed.yaml"
    path.write_text(f"{text}\nsurface: {{shape: sphere}}\ngrid: {{size: 24}}\n")
    assert cli.main(["run", str(path), "--out", str(tmp_path / "out")]) == cli.EXIT_USAGE
    key = text.splitlines()[-1].split(":")[0]
    assert f"config error: {key}: must be text" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("text, key", [("grid: {size: 032}", "grid.size"),
                                       ("signal: {gray: 'yes'}", "signal.gray"),
                                       ("grid: {size: 24}\nsignal: {seed: 0x10}", "signal.seed")])
def test_numbers_and_booleans_in_a_file_are_taken_as_written_or_refused(text, key, tmp_path,
                                                                         capsys):
    """``size: 032`` ran 26 nodes, ``gray: 'yes'`` ran as true."""
    path = tmp_path / "typed.yaml"
    path.write_text(f"name: typed\nsurface: {{shape: sphere}}\n{text}\n")
    assert cli.main(["run", str(path), "--out", str(tmp_path / "out")]) == cli.EXIT_USAGE
    assert f"config error: {key}:" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_a_relative_path_given_with_set_names_a_file_of_the_current_folder(tmp_path, monkeypatch):
    """``--set signal.image=mine.png`` on a shipped config was looked up in the package's
    folder; a file of the current folder is taken now."""
    image = np.zeros((8, 8, 3))
    image[:, :4] = 1.0
    mpimg.imsave(tmp_path / "mine.png", image)
    monkeypatch.chdir(tmp_path)
    experiment, _ = config.load("heat_sphere", ["signal.image=mine.png"])
    assert experiment.signal.image == str((tmp_path / "mine.png").resolve())
    experiment, _ = config.load("heat_sphere", ["signal.image=checker"])
    assert experiment.signal.image == "checker"  # no such file here: a built-in name


def test_ctrl_c_exits_130_with_one_line(monkeypatch, capsys):
    def interrupted(argv=None):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "main", interrupted)
    with pytest.raises(SystemExit) as stop:
        cli.entry_point()
    assert stop.value.code == 130
    assert capsys.readouterr().err == "torchsurf: interrupted\n"


def test_text_settings_are_taken_as_written():
    # YAML read name=yes as True (pictures named True.png) and name=010 as 8
    for text in ("yes", "010", "1e3", "0x10", "null_model"):
        experiment, _ = config.load("heat_sphere", [f"name={text}"])
        assert experiment.name == text
    experiment, _ = config.load("heat_sphere", ["flow.method=null", "name='quoted'"])
    assert experiment.flow.method is None and experiment.name == "quoted"


def test_quiet_also_hides_the_progress_bar(tmp_path, monkeypatch):
    from torchsurf import experiment

    asked = {}

    def recording(prepared, out, progress=False, log=print, command=None):
        asked["progress"] = progress
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "_progress_wanted", lambda disabled: not disabled)
    monkeypatch.setattr(experiment, "run", recording)
    with pytest.raises(KeyboardInterrupt):
        cli.main(["run", "heat_sphere", "--set", *TINY, "--quiet", "--out", str(tmp_path)])
    assert asked == {"progress": False}


def test_quiet_also_silences_warnings_and_an_empty_out_is_refused(tmp_path, capsys):
    # one Euler step beyond the stable step: a RuntimeWarning that --quiet ("nothing but
    # errors") still printed
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert cli.main(["run", "heat_sphere", "--set", "grid.size=20", "flow.method=euler",
                         "flow.steps=1", "--quiet", "--out", str(tmp_path / "q")]) == cli.EXIT_OK
    assert caught == []
    assert capsys.readouterr() == ("", "")
    # --out "" fell back to outputs/<name> without a word
    assert cli.main(["run", "heat_sphere", "--out", ""]) == cli.EXIT_USAGE
    assert "--out must name a folder" in capsys.readouterr().err


def test_an_unstable_step_is_warned_of_once_for_all_channels(tmp_path):
    """The heat flow ran the image's three channels one at a time and warned of its unstable
    step once per channel."""
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert cli.main(["run", "heat_sphere", "--set", *TINY, "flow.method=euler",
                         "flow.steps=1", "--out", str(tmp_path)]) == cli.EXIT_OK
    unstable = [w for w in caught if "exceeds the stable explicit step" in str(w.message)]
    assert len(unstable) == 1


def test_the_renderer_is_loaded_before_any_folder_is_made(tmp_path, monkeypatch):
    """VTK's import, reached after the flow, segfaulted when interrupted (5 of 9 tries) and
    left the empty output folder behind: it now runs before the folder is made."""
    from torchsurf import render

    resolve = render.resolve_renderer
    folder_made = []

    def watched(renderer="auto"):
        folder_made.append((tmp_path / "a").exists())
        return resolve(renderer)

    monkeypatch.setattr(render, "resolve_renderer", watched)
    code = cli.main(["run", "heat_sphere", "--set", *TINY, "render.renderer=matplotlib",
                     "--quiet", "--out", str(tmp_path / "a" / "b")])
    assert code == cli.EXIT_OK
    assert folder_made[0] is False


def test_a_stop_after_the_picture_is_drawn_leaves_no_file(tmp_path, monkeypatch):
    """The aside picture was made before the cleanup's try began: a stop in between left a
    hidden file in --out."""
    from torchsurf import render

    drawn = render.render_panels

    def stopped(*args, **kwargs):
        drawn(*args, **kwargs)
        raise KeyboardInterrupt

    monkeypatch.setattr(render, "render_panels", stopped)
    with pytest.raises(KeyboardInterrupt):
        cli.main(["run", "heat_sphere", "--set", *TINY, "--quiet", "--out", str(tmp_path)])
    assert list(tmp_path.iterdir()) == []


def test_an_interrupt_between_the_renames_waits_for_both(tmp_path, monkeypatch):
    """SIGTERM after the picture's rename and before the record's left the new picture beside
    the old record: it is now taken once both are in place."""
    import signal

    from torchsurf import experiment

    class Stopped(Exception):
        pass

    def stop(number, frame):  # noqa: ANN001, ANN202
        raise Stopped

    (tmp_path / "heat_sphere.png").write_text("old")
    (tmp_path / "heat_sphere.json").write_text("old")
    rename = os.replace

    def interrupted(source, target):  # noqa: ANN001, ANN202
        rename(source, target)
        if Path(target) == tmp_path / "heat_sphere.png":
            signal.raise_signal(signal.SIGTERM)

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        monkeypatch.setattr(experiment.os, "replace", interrupted)
        with pytest.raises(Stopped):
            cli.main(["run", "heat_sphere", "--set", *TINY, "--quiet", "--out", str(tmp_path)])
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["heat_sphere.json", "heat_sphere.png"]
    assert all(p.read_bytes() != b"old" for p in tmp_path.iterdir())


def test_list_into_a_reader_that_stops_early_is_quiet(tmp_path):
    reader = subprocess.Popen([sys.executable, "-m", "torchsurf", "list"],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    reader.stdout.close()  # before the interpreter has started: its listing meets a closed pipe
    assert reader.wait(timeout=120) == cli.EXIT_OK
    assert reader.stderr.read() == b""


def test_a_run_into_a_reader_that_stops_early_still_writes_its_files(tmp_path):
    """``torchsurf run ... | head -1``: the log's next line met a closed pipe, and the run
    ended as failed (exit 1) with nothing written; losing the log no longer loses the run."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    out = tmp_path / "out"
    runner = subprocess.Popen([sys.executable, "-m", "torchsurf", "run", "heat_sphere", "--set",
                               *TINY, "--no-progress", "--out", str(out)],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
                              cwd=tmp_path)
    assert runner.stdout.readline().startswith(b"heat_sphere:")
    runner.stdout.close()
    assert runner.wait(timeout=300) == cli.EXIT_OK, runner.stderr.read().decode()
    assert sorted(p.name for p in out.iterdir()) == ["heat_sphere.json", "heat_sphere.png"]


def test_warnings_during_a_run_are_one_line_without_pythons_location(tmp_path):
    """From the command line the library's warnings named ``<frozen runpy>:88`` (the first
    frame outside torchsurf) and printed the source line; now ``torchsurf: <category>: ...``."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=3)
    opened = trimesh.Trimesh(sphere.vertices, sphere.faces[sphere.triangles_center[:, 2] > 0])
    opened.export(tmp_path / "opened.ply")
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    done = subprocess.run([sys.executable, "-m", "torchsurf", "run", "heat_bunny", "--set",
                           f"surface.mesh={tmp_path / 'opened.ply'}", *TINY, "--no-progress",
                           "--out", str(tmp_path / "out")], capture_output=True, text=True,
                          env=env, cwd=tmp_path, timeout=300)
    assert done.returncode == cli.EXIT_OK, done.stderr
    err = done.stderr
    assert "torchsurf: RuntimeWarning: mesh: open, with an opening wider than the band" in err
    assert "runpy" not in err and "warnings.warn" not in err
    quiet = subprocess.run([sys.executable, "-m", "torchsurf", "run", "heat_bunny", "--set",
                            f"surface.mesh={tmp_path / 'opened.ply'}", *TINY, "--quiet",
                            "--out", str(tmp_path / "out")], capture_output=True, text=True,
                           env=env, cwd=tmp_path, timeout=300)
    assert quiet.returncode == cli.EXIT_OK and quiet.stderr == "" and quiet.stdout == ""


def test_usage_errors_exit_2(capsys):
    assert cli.main([]) == cli.EXIT_USAGE
    assert cli.main(["paint"]) == cli.EXIT_USAGE
    assert cli.main(["run"]) == cli.EXIT_USAGE
    assert cli.main(["--help"]) == cli.EXIT_OK
    assert cli.main(["run", "--set", "grid.size=24"]) == cli.EXIT_USAGE
    assert "required: config" in capsys.readouterr().err
    assert cli.main(["run", "--set", "heat_sphere", "tv_torus"]) == cli.EXIT_USAGE
    assert "'heat_sphere', 'tv_torus'" in capsys.readouterr().err


def test_set_before_the_config_name_leaves_the_name_to_the_config(tmp_path):
    code = cli.main(["run", "--set", *TINY, "flow.time=0.002", "heat_sphere", "--out",
                     str(tmp_path), "--quiet"])
    assert code == cli.EXIT_OK
    record = json.loads((tmp_path / "heat_sphere.json").read_text())
    assert record["config"]["grid"]["size"] == 24
    assert record["config"]["flow"]["time"] == 0.002


def test_list_names_every_shipped_config(capsys):
    assert cli.main(["list"]) == cli.EXIT_OK
    printed = capsys.readouterr().out
    for name in config.builtin_names():
        assert name in printed


def test_python_dash_m_torchsurf_exit_codes(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    refused = subprocess.run([sys.executable, "-m", "torchsurf", "run", "heat_sphere", "--set",
                              "flow.eps=1"], capture_output=True, text=True, env=env,
                             cwd=tmp_path, timeout=120)
    assert refused.returncode == 2 and "flow.eps" in refused.stderr


def test_scale_free_time_gives_the_same_run_on_a_scaled_shape(tmp_path):
    from torchsurf import experiment

    small, _ = config.load("heat_sphere", TINY)
    physical_one = experiment.physical_settings(small, diagonal=2.0, spacing=0.1)
    physical_ten = experiment.physical_settings(small, diagonal=20.0, spacing=1.0)
    assert physical_ten["time"] == pytest.approx(100 * physical_one["time"])
    tv, _ = config.load("tv_torus", TINY)
    one = experiment.physical_settings(tv, diagonal=2.0, spacing=0.1)
    ten = experiment.physical_settings(tv, diagonal=20.0, spacing=1.0)
    assert ten["time"] == pytest.approx(10 * one["time"])
    assert ten["eps"] == pytest.approx(one["eps"] / 10)
    assert np.isfinite(list(one.values())).all()


@pytest.mark.parametrize("p", [1.0, 2.0])
def test_colour_denoising_runs_the_same_on_a_sphere_a_hundred_times_smaller(tmp_path, p):
    """Its chroma is a p-harmonic map flow, whose time scales as L^p: given the brightness's
    time x L, p = 2 on a sphere of radius 0.01 took 53 chroma steps where radius 1 took 4, and
    doubled the input's error (0.121 -> 0.249)."""
    from torchsurf import experiment

    errors = []
    for radius in (1.0, 0.01):
        prepared = experiment.prepare("color_sphere", [
            "grid.size=20", f"flow.p={p}", f"surface.params.radius={radius}",
            "render.width=16", "render.height=16"])
        record = experiment.run(prepared, tmp_path / f"{radius:g}", log=lambda message: None)
        errors.append(record.metrics["rms_output"])
        diagonal = json.loads(record.record.read_text())["diagonal"]
        assert record.physical["chroma_time"] == pytest.approx(
            record.physical["time"] * diagonal ** (p - 1))
    assert errors[1] == pytest.approx(errors[0], rel=1e-3)


def test_a_time_far_beyond_equilibrium_is_a_config_error_in_the_configs_unit(tmp_path, capsys):
    """It failed with exit 1 after the surface was built, naming world units squared while the
    config gave diagonal units."""
    out = tmp_path / "out"
    code = cli.main(["run", "heat_sphere", "--set", "grid.size=20", "flow.time=100",
                     "render.width=16", "render.height=16", "--out", str(out), "--quiet"])
    error = capsys.readouterr().err
    assert code == 2 and "config error: flow.time: 100 (diagonal)" in error
    assert "times the time the diffusion takes to cross" in error and not out.exists()


def test_a_mesh_that_puts_no_surface_on_the_grid_is_a_config_error(tmp_path, capsys):
    """A single triangle read as a mesh, and failed mid-run with exit 1 naming no setting."""
    flat = tmp_path / "flat.obj"
    flat.write_text("v -0.5 -0.5 0\nv 0.5 -0.5 0\nv 0 0.5 0\nf 1 2 3\n")
    out = tmp_path / "out"
    code = cli.main(["run", "heat_sphere", "--set", "surface.shape=mesh",
                     f"surface.mesh={flat}", "grid.size=20", "--out", str(out), "--quiet"])
    error = capsys.readouterr().err
    assert code == 2 and "config error: surface.mesh:" in error and "no node" in error
    assert not out.exists()


def test_perona_malik_denoises_a_torus_a_thousand_units_across_as_one_of_size_one(tmp_path):
    """Its eps was the flows' default, 1e-2 data per world length: on shapes hundreds of units
    across it outweighed the gradients and the flow left the noise (48^3, scaled by 1e4: 0.200
    against 0.147 after the flow)."""
    from torchsurf import experiment

    errors = []
    for scale in (1.0, 1e4):
        prepared = experiment.prepare("perona_malik_torus", [
            "grid.size=20", f"surface.params.major_radius={scale}",
            f"surface.params.minor_radius={0.4 * scale}", "render.width=16", "render.height=16"])
        record = experiment.run(prepared, tmp_path / f"{scale:g}", log=lambda message: None)
        errors.append(record.metrics["rms_output"])
        assert record.physical["eps"] == pytest.approx(0.01 * record.physical["contrast"])
    assert errors[1] == pytest.approx(errors[0], rel=1e-4)


def test_a_shape_far_from_the_origin_runs_as_at_the_origin(tmp_path):
    """The grid lay at the shape in world coordinates: float32 points 5e5 from the origin are
    0.03 apart, more than the cells of a sphere of radius 1e-3, whose checkerboard came out
    as stripes (rms 0.1565 against 0.1807); the run now computes about the shape's centre."""
    import json

    from torchsurf import experiment

    metrics = []
    for centre in ("[0, 0, 0]", "[5e5, 0, 0]"):
        prepared = experiment.prepare("tv_torus", [
            "grid.size=20", "surface.shape=sphere", "surface.params={radius: 1e-3}",
            f"surface.params.center={centre}", "render.width=16", "render.height=16"])
        folder = tmp_path / centre[1]
        record = experiment.run(prepared, folder, log=lambda message: None)
        metrics.append(record.metrics)
    assert metrics[1] == pytest.approx(metrics[0], rel=1e-6)
    origin = json.loads((folder / "tv_torus.json").read_text())["grid"]["origin"]
    assert origin[0] == pytest.approx(5e5 - 1.3e-3, abs=1e-6)  # the record stays in world units


def test_a_tiny_mesh_is_moved_where_the_record_says(tmp_path):
    """trimesh's apply_translation skips a move within 1e-8 of the identity: a mesh 1e-9
    across stayed in place while the record's origin assumed it had moved (9 cells off)."""
    import json

    import trimesh

    from torchsurf import experiment, mesh

    tiny = trimesh.creation.icosphere(subdivisions=2)
    tiny.vertices = tiny.vertices * 5e-10 + 7e-10
    path = tmp_path / "tiny.ply"  # binary: the coordinates kept exactly
    tiny.export(path)
    prepared = experiment.prepare("heat_bunny", [f"surface.mesh={path}", *TINY,
                                                 "grid.layout=dense"])
    experiment.run(prepared, tmp_path / "out", log=lambda message: None)
    record = json.loads((tmp_path / "out" / "heat_bunny.json").read_text())
    expected = mesh.fit_grid(tiny, 24, prepared.experiment.grid.margin)
    spacing = record["grid"]["spacing"]
    assert spacing == pytest.approx(expected.spacing, rel=1e-9)
    assert record["grid"]["origin"] == pytest.approx(list(expected.origin), abs=1e-3 * spacing)


def test_layout_auto_takes_bricks_on_large_grids():
    experiment, _ = config.load("heat_sphere")
    assert experiment.grid.layout is config.Layout.auto
    experiment.grid.size = config.BRICKS_FROM - 1
    assert config.layout(experiment.grid) is config.Layout.dense
    experiment.grid.size = config.BRICKS_FROM
    assert config.layout(experiment.grid) is config.Layout.bricks
    experiment.grid.layout = config.Layout.dense
    assert config.layout(experiment.grid) is config.Layout.dense
    # below BRICKS_ALWAYS_FROM a margin too small for bricks keeps the dense volume; from
    # there bricks, and the margin is refused naming grid.layout=dense
    experiment.grid.layout = config.Layout.auto
    experiment.grid.margin = 0.05
    assert config.layout(experiment.grid) is config.Layout.dense
    config.check(experiment)
    experiment.grid.size = config.BRICKS_ALWAYS_FROM
    experiment.grid.margin = 0.02
    assert config.layout(experiment.grid) is config.Layout.bricks
    with pytest.raises(config.ConfigError, match="grid.margin.*grid.layout=dense"):
        config.check(experiment)


@pytest.mark.parametrize("name", [
    "tv_torus",
    pytest.param("spots_torus", marks=pytest.mark.slow),
    pytest.param("flowvis_trefoil", marks=pytest.mark.slow),
])
def test_bricks_layout_gives_the_dense_run(name, tmp_path):
    """The same experiment on bricks: the same marching-cubes mesh, signal and flow, so the
    same numbers at the vertices to rounding (and the same picture)."""
    from torchsurf import experiment

    tiny = [*_tiny_args(name), "grid.size=32", "grid.margin=0.3"]
    results = {}
    for layout in ("dense", "bricks"):
        prepared = experiment.prepare(name, [*tiny, f"grid.layout={layout}"])
        results[layout] = experiment.run(prepared, tmp_path / layout, log=lambda m: None)
    record = json.loads(results["bricks"].record.read_text())
    assert record["grid"]["layout"] == "bricks" and record["grid"]["bricks"] > 0
    dense, packed = (mpimg.imread(results[k].picture)[..., :3] for k in ("dense", "bricks"))
    assert dense.shape == packed.shape
    assert np.abs(dense - packed).mean() < 2e-3
    for key, value in results["dense"].metrics.items():
        assert results["bricks"].metrics[key] == pytest.approx(value, abs=1e-5)


@pytest.mark.parametrize(("size", "smoothing", "floor", "expected"), [
    (256, 16.0, 64, 128), (128, 16.0, 64, 64), (64, 16.0, 64, 64), (512, 16.0, 64, 256),
    (512, 64.0, 64, 64), (256, 16.0, 0, 256), (256, 4.0, 64, 256), (128, 16.0, 96, 128),
])
def test_smoothing_runs_on_a_coarser_grid_where_it_spans_enough_cells(size, smoothing, floor,
                                                                      expected):
    field = config.FieldConfig(smoothing=smoothing, smoothing_grid=floor)
    assert config.smoothing_size(size, field) == expected


def test_bad_smoothing_grid_is_refused_with_its_key(tmp_path, capsys):
    code = cli.main(["run", "stripes_torus", "--set", "field.smoothing_grid=4",
                     "--out", str(tmp_path / "out")])
    assert code == cli.EXIT_USAGE
    assert "config error: field.smoothing_grid:" in capsys.readouterr().err


def test_an_output_folder_that_cannot_be_written_is_refused_before_any_work(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    code = cli.main(["run", "heat_sphere", "--set", *TINY, "--out", str(blocker / "sub")])
    assert code == cli.EXIT_USAGE
    captured = capsys.readouterr()
    assert "cannot write to" in captured.err and "--out" in captured.err
    assert "heat_sphere:" not in captured.out  # refused before the run logged anything


@pytest.mark.parametrize("blocked", ["heat_sphere.json", "heat_sphere.png"])
def test_a_folder_where_a_file_goes_is_refused_before_any_work(tmp_path, capsys, blocked):
    """It was found only after the surface, the flow and the picture (exit 1, minutes into a
    long run)."""
    out = tmp_path / "out"
    (out / blocked).mkdir(parents=True)
    code = cli.main(["run", "heat_sphere", "--set", *TINY, "--out", str(out)])
    assert code == cli.EXIT_USAGE
    captured = capsys.readouterr()
    assert "a folder stands where the run writes its file" in captured.err
    assert blocked in captured.err and "heat_sphere:" not in captured.out
    assert sorted(p.name for p in out.iterdir()) == [blocked]


def test_a_failed_run_leaves_no_folder_and_no_traceback(tmp_path, capsys):
    """A run refused by the memory check (a MemoryError) exits 1 with one line, and the output
    folder it had created for the run is gone again."""
    out = tmp_path / "runs" / "big"
    code = cli.main(["run", "heat_sphere", "--quiet", "--set", "grid.size=100000",
                     "--out", str(out)])
    assert code == cli.EXIT_FAILED
    error = capsys.readouterr().err
    assert error.startswith("torchsurf: run failed: MemoryError:") and "Traceback" not in error
    assert not (tmp_path / "runs").exists()


def test_a_run_that_cannot_put_its_picture_in_place_leaves_no_new_record(tmp_path):
    """The record was renamed into place before the picture: a failing rename of the picture
    (here a folder in its place) left a new record beside an old picture, or none."""
    (tmp_path / "heat_sphere.png").mkdir()
    code = cli.main(["run", "heat_sphere", "--set", *TINY, "--out", str(tmp_path), "--quiet"])
    assert code != cli.EXIT_OK
    assert sorted(p.name for p in tmp_path.iterdir()) == ["heat_sphere.png"]


def test_an_interrupted_run_takes_back_the_folders_it_made(tmp_path, monkeypatch):
    """Ctrl-C (and SIGTERM, which the console script turns into SystemExit) left the empty
    --out folders the run had created."""
    from torchsurf import experiment

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(experiment, "run", interrupted)
    with pytest.raises(KeyboardInterrupt):
        cli.main(["run", "heat_sphere", "--set", *TINY, "--out", str(tmp_path / "a" / "b")])
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "config_name, override, key",
    [("harmonic_p1_torus", "field.orient=x", "field.orient"),
     ("harmonic_p1_torus", "field.smoothing=5", "field.smoothing"),
     ("stripes_torus", "field.axis=x", "field.axis")],
)
def test_field_settings_the_fields_kind_does_not_read_are_refused(config_name, override, key):
    with pytest.raises(config.ConfigError, match=rf"^{key}: not read by field.kind"):
        config.load(config_name, [override])


def test_an_interrupt_during_the_renderer_probe_waits_for_the_probe(monkeypatch, tmp_path):
    """SIGTERM in the middle of VTK's import crashed the process (exit 139): it is now held
    until the probe returns, then taken (no folder made yet)."""
    import signal

    from torchsurf import render

    class Stopped(Exception):
        pass

    def stop(number, frame):  # noqa: ANN001, ANN202
        raise Stopped

    finished = []
    probe = render.resolve_renderer

    def interrupted(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        signal.raise_signal(signal.SIGTERM)
        result = probe(*args, **kwargs)
        finished.append(True)
        return result

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        monkeypatch.setattr(render, "resolve_renderer", interrupted)
        with pytest.raises(Stopped):
            cli.main(["run", "heat_sphere", "--set", "grid.size=20", "--out",
                      str(tmp_path / "out"), "--quiet"])
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert finished == [True]
    assert not (tmp_path / "out").exists()


def test_an_interrupt_while_the_libraries_load_stops_the_run(tmp_path):
    """trimesh guards its optional imports with ``except BaseException``: a Ctrl-C given while
    it loaded was swallowed, and the run went on and replaced the outputs (exit 0). The
    command now loads them with interrupts held, then takes the interrupt: exit 130, one line,
    nothing written. Run in a fresh process, which has not loaded trimesh yet."""
    script = f"""
import signal, sys
class CtrlC:
    def find_spec(self, name, path=None, target=None):
        if name == "trimesh.path":
            sys.meta_path.remove(self)
            signal.raise_signal(signal.SIGINT)  # the keypress, while trimesh loads
        return None
sys.meta_path.insert(0, CtrlC())
sys.argv = ["torchsurf", "run", "heat_sphere", "--set", "grid.size=20", "--out", {str(tmp_path / "out")!r}]
from torchsurf.cli import entry_point
entry_point()
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert done.returncode == 130, (done.returncode, done.stderr[-2000:])
    assert done.stderr.strip().splitlines()[-1] == "torchsurf: interrupted"
    assert not (tmp_path / "out").exists()


def test_the_config_and_the_renderer_agree_on_the_widest_picture():
    from torchsurf import config, render

    assert config.PICTURE_WIDTH_MAX == render.PICTURE_WIDTH_MAX


def test_an_open_mesh_is_said_to_be_open_where_its_rms_is_reported(tmp_path):
    """An open mesh's holes are closed by phi's sign, and the RMS at the extracted surface's
    vertices counted that invented surface with no word: TV looked as if it had made a noisy
    signal worse (0.204 -> 0.223 on spot cut open) while it bettered the mesh's part."""
    from torchsurf import experiment

    ball = trimesh.creation.icosphere(subdivisions=3)
    ball.export(tmp_path / "closed.obj")
    kept = ball.triangles_center[:, 2] < 0.6
    trimesh.Trimesh(ball.vertices, ball.faces[kept]).export(tmp_path / "open.obj")
    lines = {}
    for name in ("closed", "open"):
        prepared = experiment.prepare("heat_sphere", [
            "surface.shape=mesh", f"surface.mesh={tmp_path / name}.obj", "grid.size=20",
            "render.width=16", "render.height=16"])
        holes = experiment.open_edges(prepared)
        assert (holes > 0) == (name == "open")
        logged = []
        experiment.run(prepared, tmp_path / name, log=logged.append)
        lines[name] = [line for line in logged if "is open" in line]
    assert not lines["closed"]
    assert len(lines["open"]) == 1 and f"({holes} edges of one face only)" in lines["open"][0]
    # closed by position: a texture seam's second vertex at a point, a face [a, a, b]
    vertices, faces = np.asarray(ball.vertices), np.asarray(ball.faces).copy()
    seam = len(vertices)
    touching = np.flatnonzero((faces == 0).any(axis=1))[:2]  # two of vertex 0's faces
    faces[touching] = np.where(faces[touching] == 0, seam, faces[touching])
    faces = np.concatenate([faces, [[1, 1, 2]]])
    seamed = trimesh.Trimesh(np.concatenate([vertices, vertices[:1]]), faces, process=False)
    assert len(trimesh.grouping.group_rows(seamed.edges_sorted, require_count=1)) > 0
    assert experiment.open_edges(dataclasses.replace(prepared, mesh=seamed)) == 0
