"""merge_batch (bucketed vmap, per-pair status) and the manifest runner (resume, summary CSV,
bad pairs recorded while the rest complete; groups of N maps as merge_many jobs), in process
and on a Dask LocalCluster."""

from __future__ import annotations

import contextlib
import csv
import fcntl
import json
import math
import os
import socket

import jax
import numpy as np
import pytest

from octomerge_jax import tree
from octomerge_jax.cli import main
from octomerge_jax.cli.manifest import read_manifest, run_manifest
from octomerge_jax.io import load, save
from octomerge_jax.pipeline import MergeConfig, merge, merge_batch, merge_many, transform_from_xyz_rpy

from test_pipeline import T_TRUE, perturbed, robot_map, small_pair


def test_merge_batch_matches_merge_and_isolates_bad_pairs():
    m1, m2, T = small_pair()
    coarse = robot_map((0.8, 9.0), res=0.2)
    bad_T = T.copy()
    bad_T[2, 3] = math.inf
    g2 = perturbed(-0.05, 0.08, -0.08)
    pairs = [(m1, m2, perturbed(), T), (m1, coarse, T), (m1, m2, g2, T), (m1, m2, bad_T),
             (m1, m2, transform_from_xyz_rpy(90.0, 0, 0, 0, 0, 0))]
    icp = MergeConfig().replace(registration={"refine": "icp"})  # the ICP path, batched and single
    res = merge_batch(pairs, config=icp)
    assert [r.status for r in res] == ["ok", "error", "ok", "error", "error"]
    assert [r.kind for r in res[1:2] + res[3:]] == ["resolution", "transform", "no_overlap"]
    assert "resolutions differ" in res[1].message and "NaN or infinite" in res[3].message
    for k in (0, 2):  # guesses at epsilon_t 0.150 / 0.130 m; merges reach ~0.02 / 0.03 m
        r = res[k].report
        assert r.epsilon_r < 0.05 and r.epsilon_t < 0.06, (r.epsilon_r, r.epsilon_t)
        assert r.epsilon_t < r.epsilon_t_init / 2.5
    # ... and give what a single merge gives
    single, rep = merge(m1, m2, perturbed(), T_1_2_true=T, config=icp)
    b = res[0].report
    np.testing.assert_allclose(b.T_1_2, rep.T_1_2, atol=2e-4)
    # same algorithm and stopping rule; last-bit float differences under vmap can move the
    # stopping iteration of the accelerated ICP by one or two
    assert abs(b.icp["num_iterations"] - rep.icp["num_iterations"]) <= 3
    if np.array_equal(b.T_1_2, rep.T_1_2):
        assert tree.equal(res[0].merged, single)
    else:  # float32 reductions may differ in the last bit under vmap
        assert abs(res[0].merged.num_leaves - single.num_leaves) <= 0.01 * single.num_leaves


GUESS = (T_TRUE[0, 3] + 0.1, T_TRUE[1, 3] - 0.05, 0, 0, 0, math.pi / 4 + 0.1)


def _write_manifest(tmp_path, rows):
    path = tmp_path / "pairs.csv"
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["map1", "map2", "output", "x", "y", "z", "roll", "pitch", "yaw",
                    "true_x", "true_y", "true_z", "true_roll", "true_pitch", "true_yaw"])
        w.writerows(rows)
    return path


@pytest.fixture(scope="module")
def manifest(tmp_path_factory):
    d = tmp_path_factory.mktemp("batch")
    m1, m2, T = small_pair()
    (d / "maps").mkdir()
    save(m1, d / "maps" / "a.ot")
    save(m2, d / "maps" / "b.ot")
    g = list(GUESS)
    t = [T_TRUE[0, 3], T_TRUE[1, 3], 0, 0, 0, math.pi / 4]
    rows = [["maps/a.ot", "maps/b.ot", "ab.bt", *g, *t],
            ["maps/a.ot", "maps/missing.ot", "bad.bt", *g, "", "", "", "", "", ""],
            ["maps/b.ot", "maps/a.ot", "ba.ot", 0, 0, 0, 0, 0, 0, "", "", "", "", "", ""]]
    return d, _write_manifest(d, rows)


def _summary(out_dir):
    with open(out_dir / "summary.csv", newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def local(manifest):
    """The manifest run in this process (the reference for the Dask run's bytes)."""
    d, path = manifest
    return run_manifest(path, d / "out_local", progress=False)


def test_manifest_in_process_resumable(manifest, local, capsys):

    d, path = manifest
    out, rows = d / "out_local", local
    assert [r["status"] for r in rows] == ["ok", "error", "ok"]
    assert "missing.ot: no such file" in rows[1]["message"]
    assert float(rows[0]["epsilon_r"]) < float(rows[0]["epsilon_r_init"])
    assert load(out / "ab.bt").num_leaves > 1000 and (out / "ab.bt.json").is_file()
    assert [r["status"] for r in _summary(out)] == ["ok", "error", "ok"]
    # resume: finished outputs are skipped (not rewritten) keeping their figures, the bad pair is retried
    mtime = (out / "ab.bt").stat().st_mtime_ns
    again = run_manifest(path, out, progress=True)
    assert "merging" in capsys.readouterr().err  # progress bar on stderr
    assert [r["status"] for r in again] == ["skipped", "error", "skipped"]
    assert (out / "ab.bt").stat().st_mtime_ns == mtime
    assert again[0]["epsilon_r"] == rows[0]["epsilon_r"] and again[0]["leaves_merged"] == str(rows[0]["leaves_merged"])


def test_manifest_errors(tmp_path):

    p = tmp_path / "m.csv"
    p.write_text("map1,map2\na.bt,b.bt\n")
    with pytest.raises(ValueError, match="missing column"):
        read_manifest(p, tmp_path)
    p.write_bytes(b"map1,map2,output\n\xff\n")
    with pytest.raises(ValueError, match="not UTF-8"):
        read_manifest(p, tmp_path)


def _rows(tmp_path, text):
    p = tmp_path / "m.csv"
    p.write_text(text)
    return read_manifest(p, tmp_path / "out")


GOOD_ROW = "a.bt,b.bt,fine.bt,0,0,0,0,0,0\n"


@pytest.mark.parametrize("row, message", [
    ("a.bt,b.bt,../../x.bt,0,0,0,0,0,0", "output ../../x.bt is outside --out-dir"),
    ("a.bt,b.bt,/tmp/abs.bt,0,0,0,0,0,0", "output /tmp/abs.bt is outside --out-dir"),
    ("a.bt,b.bt,esc/x.bt,0,0,0,0,0,0", "output esc/x.bt is outside --out-dir"),  # esc: a symlink out
    ("a.bt,b.bt,o.txt,0,0,0,0,0,0", "output o.txt must end in .bt or .ot"),
    ("a.bt,b.bt", "2 fields, the header has 9"),
    ("a.bt,b.bt,o.bt,0,0,0,0,0,0,7", "10 fields, the header has 9"),
    ("a.bt,b.bt,o.bt,abc,0,0,0,0,0", "x = 'abc' is not a number"),
    ("a.bt,b.bt,o.bt,0,0,nan,0,0,0", "z = 'nan' is not a finite number"),
    ("a.bt,b.bt,o.bt,0,0,0,0,0,1_0", "yaw = '1_0' is not a finite number"),
    ("a.bt,b.bt,,0,0,0,0,0,0", "must not be empty"),
    ("a.bt,b.bt,fine.bt,0,0,0,0,0,0", "output fine.bt appears twice"),
    ("out/in.bt,b.bt,in.bt,0,0,0,0,0,0", "output in.bt is also an input"),
    ("out/in.bt.json,b.bt,in.bt,0,0,0,0,0,0", "output in.bt.json is also an input"),  # its report
], ids=["dotdot", "absolute", "symlink", "suffix", "too-few", "too-many", "not-a-number", "nan", "underscore",
        "empty", "twice", "output-is-input", "report-is-input"])
def test_bad_manifest_row_is_an_error_for_that_row_only(tmp_path, row, message):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "esc").symlink_to(tmp_path)
    header = "map1,map2,output,x,y,z,roll,pitch,yaw\n"
    rows = _rows(tmp_path, header + GOOD_ROW + row + "\n" + GOOD_ROW.replace("fine", "fine2"))
    assert [bool(r.error) for r in rows] == [False, True, False]
    assert rows[1].error.startswith(f"{tmp_path / 'm.csv'}:3: ") and message in rows[1].error, rows[1].error
    assert rows[2].output == str((tmp_path / "out" / "fine2.bt").resolve())


def test_manifest_with_byte_order_mark_and_spaced_header(tmp_path):
    rows = _rows(tmp_path, "\ufeffmap1, map2 ,output,yaw\n a.bt ,b.bt,o.ot,0.5\n")
    assert len(rows) == 1 and not rows[0].error and rows[0].guess[5] == 0.5
    assert rows[0].map1 == str((tmp_path / "a.bt").resolve())


def test_manifest_on_dask_local_cluster(manifest, local):

    distributed = pytest.importorskip("distributed")
    d, path = manifest
    out = d / "out_dask"
    with _hold_port(8787), distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address="127.0.0.1:0") as cluster, distributed.Client(cluster) as client:
        rows = run_manifest(path, out, scheduler=client, progress=False)
        assert len(client.scheduler_info()["workers"]) == 2
    assert [r["status"] for r in rows] == ["ok", "error", "ok"]
    assert load(out / "ab.bt").num_leaves > 1000
    for name in ("ab.bt", "ba.ot"):  # same bytes as the in-process run
        assert (out / name).read_bytes() == (d / "out_local" / name).read_bytes(), name


@contextlib.contextmanager
def _hold_port(port):
    """Keep ``port`` busy on this machine (a dashboard's default) while the block runs, if it
    is free; the code under test must not need it."""
    sock = socket.socket()
    try:
        sock.bind(("127.0.0.1", port))
        sock.listen(1)
    except OSError:
        pass  # already taken by someone else: the condition under test anyway
    try:
        yield
    finally:
        sock.close()


def _batch(tmp_path, rows, *args):
    path = tmp_path / "pairs.csv"
    path.write_text("map1,map2,output,x,y,z,roll,pitch,yaw\n"
                    + "".join(r + ("" if r.count(",") > 2 else ",0,0,0,0,0,0") + "\n" for r in rows))
    # JAX's default promotion, as the command has (and as `local` and the Dask worker threads,
    # outside conftest's strict context): their compiled kernels are reused, not compiled again
    with jax.numpy_dtype_promotion("standard"):
        return main(["batch", str(path), "--out-dir", str(tmp_path / "out"), "--no-progress", *args])


def test_batch_command_reports_resume_and_exit_codes(manifest, local, tmp_path, capsys):
    d, _ = manifest
    a, b = d / "maps" / "a.ot", d / "maps" / "b.ot"
    out = tmp_path / "out"
    g = ",".join(map(str, GUESS))  # the pair `local` merged: its compiled kernels are reused
    pairs = [f"{a},{b},x.bt,{g}", f"{a},{b},x.ot,{g}", f"{a},{tmp_path / 'missing.ot'},m.bt"]
    assert _batch(tmp_path, pairs) == 6  # a failing pair: exit 6, the others done
    assert "3 pairs: 1 error, 2 ok" in capsys.readouterr().out
    assert (out / "x.bt.json").is_file() and (out / "x.ot.json").is_file()  # one report per output
    assert (out / "x.bt").read_bytes() == (d / "out_local" / "ab.bt").read_bytes()
    first = _summary(out)
    # a run killed between a map and its report: the pair is not finished, resume redoes it
    (out / "x.ot.json").unlink()
    mtime = (out / "x.bt").stat().st_mtime_ns
    assert _batch(tmp_path, pairs) == 6
    assert [r["status"] for r in _summary(out)] == ["skipped", "ok", "error"]
    assert (out / "x.ot.json").is_file() and (out / "x.bt").stat().st_mtime_ns == mtime
    # a resumed run of a shorter manifest keeps every earlier row
    assert _batch(tmp_path, pairs[:1]) == 0
    rows = _summary(out)
    assert [(r["output"].rsplit("/", 1)[1], r["status"]) for r in rows] == [
        ("x.bt", "skipped"), ("x.ot", "ok"), ("m.bt", "error")]
    assert rows[0]["leaves_merged"] == first[0]["leaves_merged"] != ""
    # --no-resume redoes a finished pair
    assert _batch(tmp_path, pairs[:1], "--no-resume") == 0
    assert _summary(out)[0]["status"] == "ok" and (out / "x.bt").stat().st_mtime_ns != mtime


def test_batch_lock_refuses_a_second_run_and_takes_over_a_stale_one(manifest, tmp_path, capsys):
    d, _ = manifest
    out = tmp_path / "out"
    out.mkdir()
    lock = out / ".octomerge-batch.lock"
    pair = [f"{d / 'maps' / 'a.ot'},{tmp_path / 'missing.ot'},m.bt"]  # fails fast: no merge
    fd = os.open(lock, os.O_RDWR | os.O_CREAT)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)  # what a running batch holds
        os.write(fd, b"pid 4242 on elsewhere")
        assert _batch(tmp_path, pair) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "another octomerge batch (pid 4242 on elsewhere) is running" in err[0]
        assert not (out / "summary.csv").exists()
    finally:
        os.close(fd)
    lock.write_text("pid 999999999 on here\n")  # left by a killed run: nobody holds it
    assert _batch(tmp_path, pair) == 6
    assert _summary(out)[0]["status"] == "error" and not lock.exists()


def test_dask_without_workers_fails_pending_pairs_after_timeout(manifest, tmp_path):
    distributed = pytest.importorskip("distributed")
    d, path = manifest
    out = tmp_path / "out"
    cfg = MergeConfig().replace(batch={"timeout_s": 1.0})
    with distributed.LocalCluster(n_workers=0, processes=False, dashboard_address="127.0.0.1:0") as cluster, \
            distributed.Client(cluster) as client:
        rows = run_manifest(path, out, config=cfg, scheduler=client, progress=False)
    assert [(r["status"], r["kind"]) for r in rows] == [("error", "no_workers")] * 3
    assert "no Dask worker for 1 s" in rows[0]["message"]
    assert [r["kind"] for r in _summary(out)] == ["no_workers"] * 3


def test_unreachable_scheduler_is_one_line_error(manifest, tmp_path, capsys):
    d, path = manifest
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    (tmp_path / "c.toml").write_text("[batch]\ntimeout_s = 1.0\n")
    rc = main(["batch", str(path), "--out-dir", str(tmp_path / "out"), "--scheduler", f"tcp://127.0.0.1:{port}",
               "--config", str(tmp_path / "c.toml"), "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and len(err) == 1, err
    assert err[0].startswith(f"octomerge batch: error: cannot reach the Dask scheduler tcp://127.0.0.1:{port}")


def test_batch_workers_beyond_the_cpus_are_capped_with_a_warning(tmp_path, capsys):
    many = str((os.cpu_count() or 1) + 1)
    assert _batch(tmp_path, ["a.ot,b.ot,o.txt"], "--workers", many) == 6  # the one row is bad: no cluster
    err = capsys.readouterr().err
    assert f"warning: --workers {many} is more than this machine's" in err
    assert _summary(tmp_path / "out")[0]["kind"] == "manifest"


# ----------------------------------------------------------------------------- groups of N maps

GROUP_HEADER = "group,map1,map2,output,x,y,z,roll,pitch,yaw,true_x,true_y,true_z,true_roll,true_pitch,true_yaw\n"
NO_TRUTH = ",,,,,,"


def test_manifest_groups_are_read_as_one_job_each(tmp_path):
    """Rows sharing a group id become one ManifestGroup at the place of the first: its maps in
    order of first appearance, one GroupPair per row (no guess where the row gives none); rows
    with an empty group stay pairs; a pair-only manifest reads as before."""
    rows = _rows(tmp_path, GROUP_HEADER
                 + "chain,a.bt,b.bt,g.bt,1,0,0,0,0,0.5,1,0,0,0,0,0.5\n"
                 + ",a.bt,b.bt,p.bt,,,,,,,,,,,,\n"  # a pair: empty guess cells are 0
                 + "chain,b.bt,sub/c.bt,g.bt,0,2,,,,,0,2,0,0,0,0\n"
                 + "free,c.bt,a.bt,free.ot,,,,,,,,,,,,\n"
                 + "free,c.bt,b.bt,free.ot,,,,,,,,,,,,\n")
    assert [type(r).__name__ for r in rows] == ["ManifestGroup", "ManifestRow", "ManifestGroup"]
    chain, pair, free = rows
    assert (chain.index, chain.group, pair.index, free.index) == (0, "chain", 1, 3)
    assert [p.rsplit("/", 1)[1] for p in chain.maps] == ["a.bt", "b.bt", "c.bt"] and not chain.error
    assert chain.output == str((tmp_path / "out" / "g.bt").resolve()) and chain.map1 == chain.maps[0]
    assert [(p.i, p.k, p.guess) for p in chain.pairs] == [(0, 1, (1, 0, 0, 0, 0, 0.5)), (1, 2, (0, 2, 0, 0, 0, 0))]
    assert chain.guessed and chain.pairs[1].truth == (0, 2, 0, 0, 0, 0)
    assert pair.guess == (0,) * 6 and pair.group == ""
    assert [p.rsplit("/", 1)[1] for p in free.maps] == ["c.bt", "a.bt", "b.bt"]
    assert not free.guessed and [(p.i, p.k, p.truth) for p in free.pairs] == [(0, 1, None), (0, 2, None)]


@pytest.mark.parametrize("rows, message", [
    (["g,a.bt,b.bt,g.bt", "g,b.bt,c.bt,other.bt"], ":4: output other.bt is not the output of the earlier rows of group g"),
    (["g,a.bt,b.bt,g.bt", ",c.bt,d.bt,g.bt"], ":4: output g.bt appears twice"),
    (["g,a.bt,b.bt,g.bt", "g,c.bt,c.bt,g.bt"], ":4: map1 and map2 are the same map c.bt"),
    (["g,a.bt,b.bt,g.bt", "g,a.bt,b.bt,g.bt"], ": group g: a.bt and b.bt are paired twice"),
    (["g,a.bt,b.bt,g.bt,1,0,0,0,0,0", "g,b.bt,c.bt,g.bt"], ": group g: the rows' guesses (x..yaw) do not connect c.bt"),
    (["g,a.bt,b.bt,g.bt,,,,,,,0,0,0,0,0,0", "g,a.bt,c.bt,g.bt"], "the rows' truths (true_x..true_yaw) do not connect c.bt"),
    (["g,a.bt,b.bt,g.bt,1,0,0,0,0,0", "g,b.bt,c.bt,g.bt,x,0,0,0,0,0"], ":4: x = 'x' is not a number"),
    (["g,a.bt,b.bt,g.bt", "g,b.bt,a.bt,g.bt", "g,a.bt,out/g.bt,g.bt"], ":5: output g.bt is also an input"),
], ids=["two-outputs", "output-of-a-pair", "self-pair", "paired-twice", "guesses-apart", "truths-apart", "bad-number",
        "output-is-a-member"])
def test_bad_group_row_makes_its_group_an_error_only(tmp_path, rows, message):
    text = "".join(r + "," * (15 - r.count(",")) + "\n" for r in rows)
    got = _rows(tmp_path, GROUP_HEADER + "ok,a.bt,b.bt,ok.bt" + "," * 12 + "\n" + text)
    assert not got[0].error and len(got[0].pairs) == 1
    bad = [r for r in got[1:] if r.error]
    assert len(bad) == 1 and bad[0].error.startswith(str(tmp_path / "m.csv")) and message in bad[0].error, bad[0].error


def _xyz_rpy(T):
    """``x,y,z,roll,pitch,yaw`` of a transform about z (as T_TRUE)."""
    return ",".join(repr(float(v)) for v in (T[0, 3], T[1, 3], T[2, 3], 0, 0, math.atan2(T[1, 0], T[0, 0])))


def test_batch_groups_run_resume_and_fail_alone(manifest, local, tmp_path, capsys):
    """Through the command (--refine none: the guesses are the edges): a chain of three maps
    (robot 2's map again as a third robot 0.36 m / 0.2 rad further on) with guesses and truths
    in the manifest merges exactly as ``merge_many(pairs=...)`` with the same guesses does, with
    its ManyReport and one summary row; a group with a missing map and one with an unreadable
    map are error rows while the rest run; a re-run skips the finished group, and a group
    without its report is redone; the same groups as Dask tasks give the same bytes."""
    d, _ = manifest
    a, b, c = d / "maps" / "a.ot", d / "maps" / "b.ot", tmp_path / "c.ot"
    c.write_bytes(b.read_bytes())
    (tmp_path / "bad.ot").write_bytes(b"not an octree\n")
    T_2_3 = transform_from_xyz_rpy(0.3, -0.2, 0.0, 0.0, 0.0, 0.2)
    g12, g23 = _xyz_rpy(T_TRUE), _xyz_rpy(T_2_3)
    path = tmp_path / "groups.csv"
    path.write_text(GROUP_HEADER
                    + f"team,{a},{b},team.ot,{g12},{g12}\n"
                    + f"lost,{a},{b},lost.bt,{g12}{NO_TRUTH}\nlost,{b},{tmp_path / 'missing.ot'},lost.bt,{g12}{NO_TRUTH}\n"
                    + f",{a},{b},pair.ot,{g12}{NO_TRUTH}\n"
                    + f"team,{b},c.ot,team.ot,{g23},{g23}\n"
                    + f"junk,{a},{tmp_path / 'bad.ot'},junk.bt,{g12}{NO_TRUTH}\n")
    out = tmp_path / "out"

    def batch(*args):
        with jax.numpy_dtype_promotion("standard"):  # as `local`: its compiled kernels are reused
            return main(["batch", str(path), "--out-dir", str(out), "--no-progress", "--refine", "none", *args])

    assert batch() == 6
    printed = capsys.readouterr().out
    assert "1 pairs and 3 groups: 2 error, 2 ok" in printed
    assert "failed: group lost (3 maps): " in printed and "missing.ot: no such file" in printed
    rows = {r["output"].rsplit("/", 1)[1]: r for r in _summary(out)}
    assert [r["status"] for r in rows.values()] == ["ok", "error", "ok", "error"]  # manifest order
    team = rows["team.ot"]
    assert [team[k] for k in ("group", "maps", "maps_placed", "edges_kept", "edges_rejected", "refine")] == [
        "team", "3", "3", "2", "0", "none"]
    assert float(team["epsilon_r"]) < 1e-6 and float(team["epsilon_t"]) < 1e-6 and team["map2"] == ""
    assert rows["junk.bt"]["kind"] == "MapFormatError" and "bad.ot: byte 0: not an OctoMap" in rows["junk.bt"]["message"]
    assert rows["lost.bt"]["kind"] == "FileNotFoundError" and not (out / "lost.bt").exists()
    with jax.numpy_dtype_promotion("standard"):
        m1, m2 = load(a), load(b)
        ref, _ = merge_many([m1, m2, m2], pairs={(0, 1): T_TRUE, (1, 2): T_2_3}, refine="none")
    save(ref, tmp_path / "ref.ot")
    assert (out / "team.ot").read_bytes() == (tmp_path / "ref.ot").read_bytes()
    assert int(team["leaves_merged"]) == ref.num_leaves > m1.num_leaves
    rep = json.loads((out / "team.ot.json").read_text())
    assert rep["inputs"] == [str(a), str(b), str(c)] and rep["figures"]["maps_placed"] == 3
    np.testing.assert_allclose(rep["transforms"][2], T_TRUE @ T_2_3, atol=1e-9)  # chained along the rows
    assert [e["kind"] for e in rep["edges"]] == ["guess"] * 2 and {"load", "save", "fuse"} <= rep["timings"].keys()
    # resume: the finished group is skipped with its figures; without its report it is redone
    mtime = (out / "team.ot").stat().st_mtime_ns
    assert batch() == 6
    again = {r["output"].rsplit("/", 1)[1]: r for r in _summary(out)}
    assert again["team.ot"]["status"] == "skipped" and again["team.ot"]["maps_placed"] == "3"
    assert (out / "team.ot").stat().st_mtime_ns == mtime
    (out / "team.ot.json").unlink()
    assert batch() == 6
    assert {r["output"].rsplit("/", 1)[1]: r["status"] for r in _summary(out)}["team.ot"] == "ok"
    # a group is one Dask task
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address="127.0.0.1:0") as cluster, distributed.Client(cluster) as client:
        rows = run_manifest(path, tmp_path / "dask", config=MergeConfig().replace(registration={"refine": "none"}),
                            scheduler=client, progress=False)
    assert [r["status"] for r in rows] == ["ok", "error", "ok", "error"]
    assert (tmp_path / "dask" / "team.ot").read_bytes() == (out / "team.ot").read_bytes()


@pytest.mark.slow  # a registration that finds no overlap and a one-map fuse_many: ~7 s on 2 busy cores
def test_batch_group_with_no_map_placed_is_an_error(manifest, local, tmp_path):
    """A guess 50 m off: the registration finds no overlap, the prior alone places nothing, and
    the group is an error row (``no_overlap``) with no output."""
    d, _ = manifest
    a, b = d / "maps" / "a.ot", d / "maps" / "b.ot"
    path = tmp_path / "groups.csv"
    path.write_text(GROUP_HEADER + f"far,{a},{b},far.bt,50,0,0,0,0,0{NO_TRUTH}\n")
    with jax.numpy_dtype_promotion("standard"):  # as `local`: its compiled kernels are reused
        rows = run_manifest(path, tmp_path / "out", progress=False)
    assert [(r["status"], r["kind"], r["maps"]) for r in rows] == [("error", "no_overlap", 2)]
    assert "group far: no map could be placed next to" in rows[0]["message"]
    assert "edges rejected: (0, 1) registration: no_overlap" in rows[0]["message"], rows[0]["message"]
    assert not (tmp_path / "out" / "far.bt").exists() and not (tmp_path / "out" / "far.bt.json").exists()

