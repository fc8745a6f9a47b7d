"""merge_batch (bucketed vmap, per-pair status) and the manifest runner (resume, summary CSV,
bad pairs recorded while the rest complete), in process and on a Dask LocalCluster."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest

from octomerge_jax import tree
from octomerge_jax.cli.manifest import read_manifest, run_manifest
from octomerge_jax.io import load, save
from octomerge_jax.pipeline import merge, merge_batch, transform_from_xyz_rpy

from test_pipeline import T_TRUE, perturbed, robot_map, small_pair


def test_merge_batch_matches_merge_and_isolates_bad_pairs():
    m1, m2, T = small_pair()
    coarse = robot_map((0.8, 9.0), res=0.2)
    bad_T = T.copy()
    bad_T[2, 3] = math.inf
    g2 = perturbed(-0.05, 0.08, -0.08)
    pairs = [(m1, m2, perturbed(), T), (m1, coarse, T), (m1, m2, g2, T), (m1, m2, bad_T),
             (m1, m2, transform_from_xyz_rpy(90.0, 0, 0, 0, 0, 0))]
    res = merge_batch(pairs)
    assert [r.status for r in res] == ["ok", "error", "ok", "error", "error"]
    assert [r.kind for r in res[1:2] + res[3:]] == ["resolution", "transform", "no_overlap"]
    assert "resolutions differ" in res[1].message and "NaN or infinite" in res[3].message
    for k in (0, 2):  # guesses at epsilon_t 0.150 / 0.130 m; merges reach ~0.02 / 0.03 m
        r = res[k].report
        assert r.epsilon_r < 0.05 and r.epsilon_t < 0.06, (r.epsilon_r, r.epsilon_t)
        assert r.epsilon_t < r.epsilon_t_init / 2.5
    # ... and give what a single merge gives
    single, rep = merge(m1, m2, perturbed(), T_1_2_true=T)
    b = res[0].report
    np.testing.assert_allclose(b.T_1_2, rep.T_1_2, atol=2e-4)
    # same algorithm and stopping rule; last-bit float differences under vmap can move the
    # stopping iteration of the accelerated ICP by one or two
    assert abs(b.icp["num_iterations"] - rep.icp["num_iterations"]) <= 3
    if np.array_equal(b.T_1_2, rep.T_1_2):
        assert tree.equal(res[0].merged, single)
    else:  # float32 reductions may differ in the last bit under vmap
        assert abs(res[0].merged.num_leaves - single.num_leaves) <= 0.01 * single.num_leaves


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
    g = [T_TRUE[0, 3] + 0.1, T_TRUE[1, 3] - 0.05, 0, 0, 0, math.pi / 4 + 0.1]
    t = [T_TRUE[0, 3], T_TRUE[1, 3], 0, 0, 0, math.pi / 4]
    rows = [["maps/a.ot", "maps/b.ot", "ab.bt", *g, *t],
            ["maps/a.ot", "maps/missing.ot", "bad.bt", *g, "", "", "", "", "", ""],
            ["maps/b.ot", "maps/a.ot", "ba.ot", 0, 0, 0, 0, 0, 0, "", "", "", "", "", ""]]
    return d, _write_manifest(d, rows)


def _summary(out_dir):
    with open(out_dir / "summary.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_manifest_in_process_resumable(manifest, capsys):

    d, path = manifest
    out = d / "out_local"
    rows = run_manifest(path, out, progress=True)
    assert [r["status"] for r in rows] == ["ok", "error", "ok"]
    assert "missing.ot: no such file" in rows[1]["message"]
    assert float(rows[0]["epsilon_r"]) < float(rows[0]["epsilon_r_init"])
    assert load(out / "ab.bt").num_leaves > 1000 and (out / "ab.json").is_file()
    assert [r["status"] for r in _summary(out)] == ["ok", "error", "ok"]
    assert "merging" in capsys.readouterr().err  # progress bar on stderr
    # resume: finished outputs are skipped (not rewritten), the bad pair is retried
    mtime = (out / "ab.bt").stat().st_mtime_ns
    rows = run_manifest(path, out, progress=False)
    assert [r["status"] for r in rows] == ["skipped", "error", "skipped"]
    assert (out / "ab.bt").stat().st_mtime_ns == mtime


def test_manifest_errors(tmp_path):

    p = tmp_path / "m.csv"
    p.write_text("map1,map2\na.bt,b.bt\n")
    with pytest.raises(ValueError, match="missing column"):
        read_manifest(p, tmp_path)
    p.write_text("map1,map2,output,x\na.bt,b.bt,o.bt,abc\n")
    with pytest.raises(ValueError, match=r"m.csv:2: x = 'abc' is not a number"):
        read_manifest(p, tmp_path)
    p.write_text("map1,map2,output\na.bt,b.bt,o.bt\nc.bt,d.bt,o.bt\n")
    with pytest.raises(ValueError, match="appears twice"):
        read_manifest(p, tmp_path)


def test_manifest_on_dask_local_cluster(manifest):

    distributed = pytest.importorskip("distributed")
    d, path = manifest
    out = d / "out_dask"
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        rows = run_manifest(path, out, scheduler=client, progress=False)
        assert len(client.scheduler_info()["workers"]) == 2
    assert [r["status"] for r in rows] == ["ok", "error", "ok"]
    assert load(out / "ab.bt").num_leaves > 1000
    if (d / "out_local" / "ab.bt").exists():  # same bytes as the in-process run
        assert (out / "ab.bt").read_bytes() == (d / "out_local" / "ab.bt").read_bytes()
