"""``octomerge batch`` end to end through the console script (``python -m octomerge_jax``):
exit codes (0 ok, 1 bad input, 2 usage, 6 some pairs failed), ``summary.csv`` per pair,
outputs, resume, and the same bytes from a local process pool (``--workers``) and from a Dask
scheduler (``--scheduler``) as from the serial run."""

from __future__ import annotations

import csv
import os
import socket
import subprocess
import sys

import numpy as np
import pytest

import octomerge_jax as om
from helpers import voxel_log_odds

TIMEOUT_S = 600
HEADER = "map1,map2,output,x,y,z,roll,pitch,yaw\n"
ZERO = ",0,0,0,0,0,0\n"
# two good pairs, a missing input and a pair of different resolutions
MANIFEST = (HEADER + "maps/a.ot,maps/b.ot,ab.ot" + ZERO + "maps/a.ot,maps/missing.ot,am.bt" + ZERO
            + "maps/a.ot,maps/coarse.ot,ac.bt" + ZERO + "maps/b.ot,maps/a.ot,sub/ba.bt" + ZERO)
GOOD = (HEADER + "maps/a.ot,maps/b.ot,ab.ot" + ZERO + "maps/b.ot,maps/a.ot,sub/ba.bt" + ZERO)


def octomerge(*args, timeout=TIMEOUT_S):
    env = dict(os.environ)  # the run's XLA cache (tests/conftest.py)
    return subprocess.run([sys.executable, "-m", "octomerge_jax", *map(str, args)], capture_output=True,
                          text=True, timeout=timeout, env=env)


def crop(m, mask):
    L = m.leaves()
    return om.from_leaves(L.codes[mask], L.depths[mask], L.log_odds[mask], m.resolution, params=m.params)


@pytest.fixture(scope="module")
def job(tmp_path_factory):
    """Maps (two overlapping crops of the example room, a 0.2 m map) and the manifests."""
    d = tmp_path_factory.mktemp("batch")
    (d / "maps").mkdir()
    room = om.example_map()
    c = room.leaves().centers
    a = crop(room, (c[:, 0] < 0.5) & (c[:, 1] < 0.5))
    b = crop(room, (c[:, 0] > -0.5) & (c[:, 1] < 0.5))
    om.save(a, d / "maps" / "a.ot")
    om.save(b, d / "maps" / "b.ot")
    L = a.leaves()
    om.save(om.from_leaves(L.codes, L.depths, L.log_odds, 0.2), d / "maps" / "coarse.ot")
    (d / "pairs.csv").write_text(MANIFEST)
    (d / "good.csv").write_text(GOOD)
    return d


@pytest.fixture(scope="module")
def serial(job):
    out = job / "serial"
    r = octomerge("batch", job / "pairs.csv", "--out-dir", out, "--refine", "none", "--no-progress")
    return r, out


def summary(out):
    with open(out / "summary.csv", newline="") as f:
        return {int(r["index"]): r for r in csv.DictReader(f)}


def test_batch_with_bad_pairs_exits_6_and_records_each_pair(job, serial):
    r, out = serial
    assert r.returncode == 6, r.stderr
    assert "4 pairs: 2 error, 2 ok" in r.stdout
    assert "failed: a.ot + missing.ot" in r.stdout and "failed: a.ot + coarse.ot" in r.stdout
    rows = summary(out)
    assert [rows[i]["status"] for i in range(4)] == ["ok", "error", "error", "ok"]
    assert rows[1]["kind"] == "FileNotFoundError" and "missing.ot: no such file" in rows[1]["message"]
    assert rows[2]["kind"] == "resolution" and "resolutions differ" in rows[2]["message"]
    assert rows[0]["refine"] == "none" and rows[0]["output"] == str((out / "ab.ot").resolve())
    # outputs of the good pairs (and their reports), nothing for the bad ones
    assert (out / "ab.ot").is_file() and (out / "sub" / "ba.bt").is_file() and (out / "ab.ot.json").is_file()
    assert not (out / "am.bt").exists() and not (out / "ac.bt").exists()
    # identity guess, no refinement: the merged map is the log-odds sum where both know a
    # voxel (clamped), the one value elsewhere
    a, b = om.load(job / "maps" / "a.ot"), om.load(job / "maps" / "b.ot")
    ca, cb = voxel_log_odds(a), voxel_log_odds(b)
    lo, hi = np.float32(a.params.clamp_min_log_odds), np.float32(a.params.clamp_max_log_odds)
    ref = {k: float(np.clip(np.float32(ca[k]) + np.float32(cb[k]), lo, hi)) if k in ca and k in cb
           else ca.get(k, cb.get(k)) for k in ca.keys() | cb.keys()}
    merged = om.load(out / "ab.ot")
    assert voxel_log_odds(merged) == ref
    assert int(rows[0]["leaves_merged"]) == merged.num_leaves
    # .bt keeps maximum likelihood: the same voxels, occupied where the sum is above threshold
    ba = voxel_log_odds(om.load(out / "sub" / "ba.bt"))
    assert ba.keys() == ref.keys()
    assert all((ba[k] > 0) == (v > 0) for k, v in ref.items())


def test_batch_resume_skips_finished_outputs(job, serial):
    _, out = serial
    before = {p: p.stat().st_mtime_ns for p in (out / "ab.ot", out / "sub" / "ba.bt")}
    r = octomerge("batch", job / "pairs.csv", "--out-dir", out, "--refine", "none", "--no-progress")
    assert r.returncode == 6, r.stderr
    assert "4 pairs: 2 error, 2 skipped" in r.stdout
    rows = summary(out)
    assert [rows[i]["status"] for i in range(4)] == ["skipped", "error", "error", "skipped"]
    assert rows[0]["message"] == "output exists (resume)"
    assert {p: p.stat().st_mtime_ns for p in before} == before


@pytest.mark.parametrize("text, args, code, message", [
    ("map1,map2,x\na.ot,b.ot,0\n", (), 1, "missing column(s) output"),
    (GOOD, ("--workers", "-1"), 2, "--workers must be >= 0, got -1"),
], ids=["missing-column", "negative-workers"])
def test_batch_bad_manifest_is_one_line_error(tmp_path, text, args, code, message):
    (tmp_path / "pairs.csv").write_text(text)
    r = octomerge("batch", tmp_path / "pairs.csv", "--out-dir", tmp_path / "out", *args)
    assert r.returncode == code
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("octomerge batch: error: ") and message in lines[0], r.stderr
    assert not (tmp_path / "out" / "summary.csv").exists()


def test_batch_missing_manifest_and_usage(tmp_path):
    r = octomerge("batch", tmp_path / "nope.csv", "--out-dir", tmp_path)
    assert r.returncode == 1 and "nope.csv: no such file" in r.stderr
    r = octomerge("batch", tmp_path / "nope.csv")  # --out-dir is required
    assert r.returncode == 2 and "--out-dir" in r.stderr


def _same_outputs(out, serial_out):
    for name in ("ab.ot", "sub/ba.bt"):
        assert (out / name).read_bytes() == (serial_out / name).read_bytes(), name


def test_batch_local_workers_equal_serial(job, serial):
    _, serial_out = serial
    out = job / "workers"
    with socket.socket() as busy:  # a Dask dashboard's default port taken: --workers must not need it
        try:
            busy.bind(("127.0.0.1", 8787))
            busy.listen(1)
        except OSError:
            pass  # taken already
        r = octomerge("batch", job / "good.csv", "--out-dir", out, "--refine", "none", "--no-progress",
                      "--workers", "1")
    assert r.returncode == 0, r.stderr
    assert "2 pairs: 2 ok" in r.stdout
    _same_outputs(out, serial_out)
    rows = summary(out)
    assert [rows[i]["status"] for i in range(2)] == ["ok", "ok"]


def test_batch_on_a_dask_scheduler_equals_serial(job, serial):
    distributed = pytest.importorskip("distributed")
    _, serial_out = serial
    out = job / "scheduler"
    # the worker is a thread of this process; tcp, so the command (another process) reaches it
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tcp",
                                  host="127.0.0.1", dashboard_address="127.0.0.1:0") as cluster:
        assert cluster.scheduler_address.startswith("tcp://")
        r = octomerge("batch", job / "good.csv", "--out-dir", out, "--refine", "none", "--no-progress",
                      "--scheduler", cluster.scheduler_address)
    assert r.returncode == 0, r.stderr
    assert "2 pairs: 2 ok" in r.stdout
    _same_outputs(out, serial_out)
