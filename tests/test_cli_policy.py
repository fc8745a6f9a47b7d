"""The command line's input / output policy and settings validation (``cli/outputs.py``,
``pipeline/config.validate``): every bad value or destination is a one-line error naming the
argument, file or key, found before any compute (these tests run no merge), and nothing is
written where it should not be."""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
import typing
from pathlib import Path

import numpy as np
import pytest

import octomerge_jax as om
from octomerge_jax.cli import build_parser, main
from octomerge_jax.cli.merge import guess_from_args
from octomerge_jax.pipeline import MergeConfig, config_from_dict, config_to_dict, load_config


@pytest.fixture(scope="module")
def maps(tmp_path_factory):
    d = tmp_path_factory.mktemp("policy")
    room = om.example_map()
    om.save(room, d / "a.ot")
    om.save(room, d / "b.ot")
    return d


@pytest.fixture
def unwritable(tmp_path):
    """A folder no file can be created in: mode 555 for a normal user; /sys for root (whom
    permissions do not stop)."""
    if os.geteuid() != 0:
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o555)
        yield ro
        ro.chmod(0o755)
    elif not _can_create_in("/sys"):
        yield Path("/sys")
    else:
        pytest.skip("no unwritable folder for root here")


def _can_create_in(folder) -> bool:
    try:
        fd, path = tempfile.mkstemp(dir=folder)
    except OSError:
        return False
    os.close(fd)
    os.unlink(path)
    return True


def one_line_error(capsys, command):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"octomerge {command}: error: "), err
    return err[0]


# ----------------------------------------------------------------------------- settings


def _numeric_keys():
    """Every numeric setting as (key, kind): kind 'int', 'float' or 'floats' (a tuple)."""
    out = []
    for section, cls in typing.get_type_hints(MergeConfig).items():
        for name, ann in typing.get_type_hints(cls).items():
            base = ([a for a in typing.get_args(ann) if a is not type(None)] or [ann])[0]
            if typing.get_origin(ann) is tuple:
                base = "floats"
            kind = {int: "int", float: "float", "floats": "floats"}.get(base)
            if kind:
                out.append((f"{section}.{name}", kind))
    return out


NUMERIC = _numeric_keys()


def test_every_numeric_setting_is_swept():
    keys = {k for k, _ in NUMERIC}
    assert {"fuse.weights", "registration.yaw_step_rad", "registration.max_iterations", "transform.chunk_bricks",
            "batch.workers", "demo.spacing", "demo.error_rpy_rad"} <= keys
    assert len(keys) >= 23


@pytest.mark.parametrize("key, kind", NUMERIC, ids=[k for k, _ in NUMERIC])
def test_numeric_setting_rejects_nan_inf_negative_and_huge(key, kind):
    section, name = key.split(".")
    default = getattr(getattr(MergeConfig(), section), name)
    bad = {"int": [-1, 2**62], "float": [math.nan, math.inf, -math.inf, -1.0, 1e300]}
    if kind == "floats":
        n = len(default)
        cases = [[v] * n for v in (math.nan, math.inf, 1e300)] + [[-1.0] * n]
    else:
        cases = bad[kind]
    for v in cases:
        if key == "demo.error_xyz" and v == [-1.0] * 3:
            continue  # a negative error is an error in the other direction
        if key == "demo.error_rpy_rad" and v == [-1.0] * 3:
            continue
        with pytest.raises(ValueError, match=key.replace(".", r"\.")):
            config_from_dict({section: {name: v}})
    if kind in ("int", "float") and default is not None:  # the default itself is fine
        config_from_dict({section: {name: default}})


@pytest.mark.parametrize("section, values", [
    ("fuse", {"rule": "weighted", "weights": [math.nan, 1.0]}),
    ("fuse", {"weights": [0.0, 0.0]}),
    ("fuse", {"weights": [-1.0, 1.0]}),
    ("fuse", {"weights": [1.0]}),
    ("registration", {"yaw_step_rad": 0.0}),
    ("registration", {"yaw_step_rad": 1e-9}),
    ("registration", {"max_iterations": 10**13}),
    ("transform", {"chunk_bricks": 10**8}),
    ("batch", {"workers": 10**6}),
    ("demo", {"spacing": 1e-6}),
    ("registration", {"min_correspondence_distance": 2.0, "max_correspondence_distance": 1.0}),
], ids=["weights-nan", "weights-zero", "weights-negative", "weights-one", "yaw-step-0", "yaw-step-1e-9",
        "max-iterations-1e13", "chunk-bricks-1e8", "workers-1e6", "demo-spacing-1e-6", "min-above-max"])
def test_issue_settings_are_one_line_errors_naming_the_key(tmp_path, capsys, section, values):
    path = tmp_path / "c.json"
    path.write_text(json.dumps({section: values}))
    assert main(["dump-config", "--config", str(path)]) == 1
    line = one_line_error(capsys, "dump-config")
    assert f"{path}: {section}." in line


def test_fuse_rejects_bad_weights_before_any_compute():
    m = om.example_map()
    for w in ((math.nan, 1.0), (0.0, 0.0), (-1.0, 1.0), (1.0,)):
        with pytest.raises(ValueError, match="weights"):
            om.fuse(m, m, "weighted", weights=w)
    with pytest.raises(ValueError, match="weights must hold one weight per map"):
        om.fuse_many([m, m, m], "weighted", weights=[1.0, 1.0])


def test_valid_settings_still_load():
    cfg = MergeConfig().replace(fuse={"rule": "weighted", "weights": (1.0, 0.0)},
                                registration={"yaw_step_rad": 0.1, "max_iterations": 500},
                                demo={"spacing": 0.25})
    assert config_from_dict(config_to_dict(cfg)) == cfg


@pytest.mark.parametrize("name, text, message", [
    ("deep.json", '{"a":' * 100_000 + "1" + "}" * 100_000, "not valid JSON"),
    ("deep.toml", "a = " + "[" * 100_000 + "]" * 100_000, "not valid TOML"),
    ("latin1.toml", "# caf\xe9\n", "not UTF-8 text (byte 5)"),
], ids=["json", "toml", "not-utf8"])
def test_unreadable_config_is_one_line_error(tmp_path, capsys, name, text, message):
    path = tmp_path / name
    path.write_bytes(text.encode("latin-1"))
    assert main(["dump-config", "--config", str(path)]) == 1
    assert f"{path}: {message}" in one_line_error(capsys, "dump-config")


def test_config_with_byte_order_mark_loads(tmp_path):
    path = tmp_path / "bom.toml"
    path.write_bytes("\ufeff[fuse]\nrule = 'max'\n".encode("utf-8"))
    assert load_config(path).fuse.rule == "max"
    assert main(["dump-config", "--config", str(path)]) == 0


def test_demo_spacing_refused_before_simulating(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--spacing", "1e-6", "--out-dir", str(out), "--no-figures"]) == 1
    assert "demo.spacing must lie in [0.1, 100], got 1e-06" in one_line_error(capsys, "demo")
    assert not out.exists()


# ----------------------------------------------------------------------------- outputs


def _commands(d, out_dir):
    a, b, manifest = str(d / "a.ot"), str(d / "b.ot"), d / "pairs.csv"
    return {
        "merge": (["merge", a, b, str(out_dir / "m.bt"), "--refine", "none"], out_dir / "m.bt"),
        "convert": (["convert", a, str(out_dir / "c.bt")], out_dir / "c.bt"),
        "export": (["export", a, str(out_dir / "e.ply")], out_dir / "e.ply"),
        "dump-config": (["dump-config", "--out", str(out_dir / "s.toml")], out_dir / "s.toml"),
        "demo": (["demo", "--out-dir", str(out_dir / "demo"), "--no-figures"], out_dir / "demo"),
        "batch": (["batch", str(manifest), "--out-dir", str(out_dir / "batch"), "--no-progress"], out_dir / "batch"),
    }


@pytest.mark.parametrize("command", ["merge", "convert", "export", "dump-config", "demo", "batch"])
def test_unwritable_destination_is_one_line_error_naming_it(maps, unwritable, capsys, command):
    (maps / "pairs.csv").write_text("map1,map2,output\na.ot,b.ot,ab.bt\n")
    argv, named = _commands(maps, unwritable)[command]
    assert main(argv) == 1
    line = one_line_error(capsys, command)
    assert str(named) in line and ".tmp" not in line
    assert not named.exists()


@pytest.mark.parametrize("command", ["merge", "convert", "export"])
def test_missing_output_folder_is_one_line_error(maps, tmp_path, capsys, command):
    argv, named = _commands(maps, tmp_path / "nope")[command]
    assert main(argv) == 1
    assert "does not exist" in one_line_error(capsys, command)


def test_convert_refuses_an_existing_output_without_force(maps, tmp_path, capsys):
    out = tmp_path / "x.bt"
    out.write_bytes(b"old")
    assert main(["convert", str(maps / "a.ot"), str(out)]) == 1
    assert f"{out} exists; pass --force to overwrite it" in one_line_error(capsys, "convert")
    assert out.read_bytes() == b"old"
    assert main(["convert", str(maps / "a.ot"), str(out), "--force"]) == 0
    assert om.load(out).num_leaves > 0


def test_convert_force_replaces_its_input(maps, tmp_path, capsys):
    src = tmp_path / "in.ot"
    shutil.copy(maps / "a.ot", src)
    assert main(["convert", str(src), str(src)]) == 1
    assert "is also an input; pass --force to overwrite it" in one_line_error(capsys, "convert")
    assert main(["convert", str(src), str(src), "--force"]) == 0
    assert om.load(src).num_leaves == om.load(maps / "a.ot").num_leaves


@pytest.mark.parametrize("extra, message", [
    (["--report", "{d}/r.json"], "r.json exists; pass --force to overwrite it"),
    (["--figure", "{t}/x.json"], "--figure must end in .png"),
    (["--map-figure", "{t}/x"], "--map-figure must end in .png"),
    (["--report", "{d}/a.ot", "--force"], "--report is also an input; refusing to overwrite it"),
    (["--report", "{t}/o.bt"], "--report is also another output"),
], ids=["report-exists", "figure-json", "figure-no-suffix", "report-is-input", "report-is-out"])
def test_merge_side_outputs_checked_before_compute(maps, tmp_path, capsys, extra, message):
    (maps / "r.json").write_text("keep")
    out = tmp_path / "o.bt"
    argv = ["merge", str(maps / "a.ot"), str(maps / "b.ot"), str(out), "--refine", "none",
            *[e.format(d=maps, t=tmp_path) for e in extra]]
    assert main(argv) == 1
    assert message in one_line_error(capsys, "merge")
    assert not out.exists() and (maps / "r.json").read_text() == "keep"


@pytest.mark.parametrize("command", ["merge", "convert", "info", "export", "batch", "merge --config"])
def test_a_directory_as_input_is_reported_as_one(maps, tmp_path, capsys, command):
    folder = tmp_path / "dir.bt"
    folder.mkdir()
    a = str(maps / "a.ot")
    argv = {"merge": ["merge", str(folder), a, str(tmp_path / "o.bt")],
            "convert": ["convert", str(folder), str(tmp_path / "o.bt")],
            "info": ["info", str(folder)],
            "export": ["export", str(folder), str(tmp_path / "o.ply")],
            "batch": ["batch", str(folder), "--out-dir", str(tmp_path / "out")],
            "merge --config": ["merge", a, a, str(tmp_path / "o.bt"), "--config", str(folder)]}[command]
    assert main(argv) == 1
    assert f"{folder}: is a directory" in one_line_error(capsys, command.split()[0])


# ----------------------------------------------------------------------------- angles


@pytest.mark.parametrize("argv, warned", [
    (["--rpy", "0", "0", "45"], "--rpy yaw = 45 rad is more than a full turn; if it is in degrees, add --degrees"),
    (["0", "0", "0", "0", "0", "1000.8"], "initial guess: yaw = 1000.8 rad is more than a full turn; if it is in degrees, add --degrees"),
    (["--rpy", "0", "0", "400", "--degrees"], "--rpy yaw = 400 degrees is more than a full turn"),
    (["--rpy", "0", "0", "6.2"], None),
    (["--rpy", "0", "0", "45", "--degrees"], None),
], ids=["45-rad", "1000.8-rad-positional", "400-deg", "6.2-rad", "45-deg"])
def test_angle_beyond_a_full_turn_warns_and_is_used(capsys, argv, warned):
    args = build_parser().parse_args(["merge", "a.bt", "b.bt", "o.bt", *argv])
    guess = guess_from_args(args)
    err = capsys.readouterr().err
    if warned is None:
        assert err == ""
    else:
        assert err.strip() == f"octomerge: warning: {warned}"
    given = [float(v) for v in argv if v.replace(".", "").isdigit()][-1]
    assert np.isclose(guess[5], math.radians(given) if "--degrees" in argv else given)
