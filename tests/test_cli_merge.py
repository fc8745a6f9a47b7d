"""``octomerge merge`` / ``dump-config`` / ``demo`` end to end through ``cli.main``: outputs,
reports, figures, exit codes and messages for bad input, never overwriting an input."""

from __future__ import annotations

import json
import math
import tomllib

import numpy as np
import pytest

from octomerge_jax.cli import main
from octomerge_jax.io import load, save

from test_pipeline import T_TRUE, robot_map, small_pair


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    m1, m2, _ = small_pair()
    save(m1, d / "a.ot")
    save(m2, d / "b.ot")
    save(robot_map((0.8, 9.0), res=0.2), d / "coarse.ot")
    return d


def _guess_args(dyaw=0.08):
    x, y = T_TRUE[0, 3] + 0.05, T_TRUE[1, 3] - 0.05
    return [f"{x}", f"{y}", "0", "0", "0", f"{math.pi / 4 + dyaw}"]


def test_merge_positional_thesis_order_with_report_and_figures(files, capsys):
    out = files / "merged.bt"
    rc = main(["merge", str(files / "a.ot"), str(files / "b.ot"), str(out), *_guess_args(),
               "--report", str(files / "r.json"), "--figure", str(files / "fig.png"),
               "--map-figure", str(files / "map.png"), "--icp-figure", str(files / "icp.png"),
               "--true-xyz", f"{T_TRUE[0, 3]}", f"{T_TRUE[1, 3]}", "0",
               "--true-rpy", "0", "0", f"{math.pi / 4}"])
    text = capsys.readouterr().out
    assert rc == 0, text
    merged = load(out)
    rep = json.loads((files / "r.json").read_text())
    assert rep["counts"]["leaves_merged"] > 0 and rep["icp"] is not None
    assert rep["epsilon_r"] < rep["epsilon_r_init"]
    assert "epsilon_r" in text and str(out) in text
    for png in ("fig.png", "map.png", "icp.png"):  # icp.png: the reported run (icp_trace checks it)
        data = (files / png).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    # .bt stores maximum likelihood: the merged map is non-trivial and in map 1's frame
    assert merged.num_leaves > 1000
    assert not list(files.glob(".merged.bt.*"))  # no temp files left behind


def test_merge_flags_refine_none_equals_guess(files):
    out = files / "none.ot"
    g = [float(v) for v in _guess_args()]
    rc = main(["merge", str(files / "a.ot"), str(files / "b.ot"), str(out), "--xyz", *map(str, g[:3]),
               "--rpy", *map(str, np.degrees(g[3:])), "--degrees", "--refine", "none",
               "--report", str(files / "none.json"), "-q"])
    assert rc == 0
    rep = json.loads((files / "none.json").read_text())
    assert rep["icp"] is None and rep["refine"] == "none"
    assert np.asarray(rep["T_1_2"])[0, 3] == pytest.approx(g[0])
    assert np.asarray(rep["T_1_2"])[1, 0] == pytest.approx(math.sin(g[5]))


def _err(capsys):
    return capsys.readouterr().err


def test_merge_bad_inputs_exit_codes(files, capsys, tmp_path):
    a, b = str(files / "a.ot"), str(files / "b.ot")
    out = str(tmp_path / "o.bt")
    assert main(["merge", a, str(files / "missing.bt"), out]) == 1
    assert "missing.bt: no such file" in _err(capsys)
    assert main(["merge", a, b, out, "0", "0", "nan", "0", "0", "0"]) == 1
    assert "z = nan is not a finite number" in _err(capsys)
    assert main(["merge", a, b, out, "1", "2"]) == 2
    assert "6 numbers" in _err(capsys)
    assert main(["merge", a, str(files / "coarse.ot"), out, *_guess_args()]) == 3
    err = _err(capsys)
    assert "resolutions differ" in err and "--resample" in err
    assert main(["merge", a, b, out, "80", "0", "0", "0", "0", "0"]) == 4
    assert "no overlap" in _err(capsys)
    assert main(["merge", a, b, str(tmp_path / "o.txt")]) == 1
    assert "must end in .bt or .ot" in _err(capsys)
    assert not (tmp_path / "o.bt").exists()


def test_merge_overwrites_an_input_only_with_force(files, capsys, tmp_path):
    a, b = files / "a.ot", files / "b.ot"
    before = a.read_bytes()
    assert main(["merge", str(a), str(b), str(a), *_guess_args()]) == 1
    assert "is also an input; pass --force to overwrite it" in _err(capsys)
    assert main(["merge", str(a), str(b), str(files / "x.bt"), "--report", str(b), "--force"]) == 1
    assert "--report is also an input; refusing" in _err(capsys)  # a side output never replaces an input
    assert a.read_bytes() == before
    # --force does what it says: OUT replaces map 1 (read completely first), e.g. to accumulate
    acc = tmp_path / "acc.ot"
    acc.write_bytes(before)
    assert main(["merge", str(acc), str(b), str(acc), *_guess_args(), "--force", "-q"]) == 0
    assert acc.read_bytes() != before and load(acc).num_leaves > load(a).num_leaves // 2
    # an existing (non-input) output needs --force
    (files / "exists.bt").write_bytes(b"old")
    assert main(["merge", str(a), str(b), str(files / "exists.bt"), *_guess_args()]) == 1
    assert "--force" in _err(capsys)
    assert (files / "exists.bt").read_bytes() == b"old"


def test_merge_strict_not_converged_exit_5(files, capsys, tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text("[registration]\nmax_iterations = 3\n")  # too few to converge
    out = tmp_path / "s.bt"
    args = ["merge", str(files / "a.ot"), str(files / "b.ot"), str(out), *_guess_args(), "--config", str(cfg)]
    assert main(args) == 0  # default: warn and use ICP's last transform
    assert "did not converge" in _err(capsys)
    assert main([*args, "--strict", "--force"]) == 5


def test_dump_config_round_trip(tmp_path, capsys):
    assert main(["dump-config"]) == 0
    text = capsys.readouterr().out
    data = tomllib.loads(text)
    assert data["registration"]["refine"] == "icp+dense" and data["fuse"]["rule"] == "sum"  # the default
    (tmp_path / "c.toml").write_text(text.replace('rule = "sum"', 'rule = "max"'))
    assert main(["dump-config", "--config", str(tmp_path / "c.toml"), "--json",
                 "--out", str(tmp_path / "c.json")]) == 0
    assert json.loads((tmp_path / "c.json").read_text())["fuse"]["rule"] == "max"
    (tmp_path / "bad.toml").write_text("[fuse]\nrul = 'max'\n")
    assert main(["dump-config", "--config", str(tmp_path / "bad.toml")]) == 1
    assert "unknown setting fuse.rul" in capsys.readouterr().err


def test_help_lists_commands(capsys):
    with pytest.raises(SystemExit):
        main(["merge", "--help"])
    text = capsys.readouterr().out
    assert "x y z roll pitch yaw" in text and "exit codes" in text


@pytest.mark.slow
def test_demo_runs(tmp_path, capsys):  # the README's main job; minutes on 2 busy cores
    rc = main(["demo", "--out-dir", str(tmp_path / "demo")])
    out = capsys.readouterr().out
    assert rc == 0, out
    rep = json.loads((tmp_path / "demo" / "report.json").read_text())
    assert rep["epsilon_r"] < 0.25 and rep["epsilon_t"] < 0.9  # thesis "coherent" limits
    assert rep["epsilon_r"] < rep["epsilon_r_init"]
    for f in ("merged.bt", "map1.bt", "map2.bt", "overlap_before_after.png", "merged_map.png"):
        assert (tmp_path / "demo" / f).is_file(), f
    assert "epsilon before ICP" in out and "epsilon after  ICP" in out


# --- bags
def test_merge_bags_in_and_out(files, tmp_path, capsys):
    """Maps from a ROS 1 bag and a ROS 2 MCAP bag merge as the same maps from files do (same
    compiled kernels as the test above), and --out-bag holds the merged map's leaves, in map 1's
    frame, at the later input stamp."""
    pytest.importorskip("rosbags")
    from octomerge_jax.io.bags import read_bag, write_bag

    a, b = load(files / "a.ot"), load(files / "b.ot")
    write_bag(tmp_path / "a.bag", a, binary=False, topic="/robot1/octomap_full", stamps_ns=[7 * 10**9], frame_id="r1")
    write_bag(tmp_path / "b_ros2", b, binary=False, topic="/robot2/octomap_full", stamps_ns=[5 * 10**9])
    args = [*_guess_args(), "--refine", "none", "-q"]
    assert main(["merge", str(files / "a.ot"), str(files / "b.ot"), str(tmp_path / "files.ot"), *args]) == 0
    assert main(["merge", str(tmp_path / "a.bag"), str(tmp_path / "b_ros2"), str(tmp_path / "bags.ot"), *args,
                 "--topic", "/robot1/octomap_full", "--topic", "/robot2/octomap_full",
                 "--out-bag", str(tmp_path / "merged.bag")]) == 0
    assert (tmp_path / "files.ot").read_bytes() == (tmp_path / "bags.ot").read_bytes()
    (got,) = read_bag(tmp_path / "merged.bag")
    assert (got.topic, got.frame_id, got.stamp_ns, got.binary) == ("/octomap_full", "r1", 7 * 10**9, False)
    want = load(tmp_path / "bags.ot").leaves()
    assert np.array_equal(got.map.leaves().codes, want.codes) and np.array_equal(got.map.leaves().log_odds, want.log_odds)
    capsys.readouterr()
    assert main(["merge", str(tmp_path / "a.bag"), str(tmp_path / "b_ros2"), str(tmp_path / "x.ot"), *args,
                 "--topic", "/robot1/octomap_full"]) == 1  # b_ros2 has no such topic
    assert main(["merge", str(files / "a.ot"), str(files / "b.ot"), str(tmp_path / "y.ot"), *args,
                 "--topic", "/t"]) == 2  # --topic without a bag input
    assert main(["merge", str(tmp_path / "a.bag"), str(tmp_path / "b_ros2"), str(tmp_path / "z.ot"), *args,
                 "--out-bag", str(tmp_path / "merged.bag")]) == 1  # --out-bag exists, no --force
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 3 and "no topic /robot1/octomap_full" in err[0] and "applies to bag inputs" in err[1], err
    assert "merged.bag exists" in err[2]


def test_dump_config_describes_every_key(capsys):
    """Every key ``dump-config`` writes is preceded by a comment describing it (from the
    section's docstring), so a new setting without documentation fails here."""
    import dataclasses

    from octomerge_jax.pipeline import MergeConfig
    from octomerge_jax.pipeline.config_file import field_docs

    cfg = MergeConfig()
    for f in dataclasses.fields(cfg):
        section = type(getattr(cfg, f.name))
        missing = [g.name for g in dataclasses.fields(section) if not field_docs(section).get(g.name)]
        assert not missing, f"[{f.name}] keys without a description: {missing}"
    assert main(["dump-config"]) == 0
    lines = capsys.readouterr().out.splitlines()
    keys = [i for i, line in enumerate(lines) if line and line[0].isalpha() and " = " in line]
    assert keys and all(lines[i - 1].startswith("#") for i in keys)
