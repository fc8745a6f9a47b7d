"""``octomerge merge``'s ``--rule``, ``--interpolation`` and ``--overlap`` through the console
script (``python -m octomerge_jax``): each accepted value does what it names (checked against
brute force or the library's public functions); a bad value is a usage error (exit 2)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial import cKDTree

import octomerge_jax as om
from helpers import voxel_log_odds

TIMEOUT_S = 600


@pytest.fixture(scope="module")
def d(tmp_path_factory):
    """Two overlapping crops of the example room (0.1 m); the command runs share the test run's
    XLA cache (tests/conftest.py), so their kernels are compiled once."""
    d = tmp_path_factory.mktemp("merge_options")
    room = om.example_map()
    c = room.leaves().centers
    for name, mask in (("a", (c[:, 0] < 0.5) & (c[:, 1] < 0.5)), ("b", (c[:, 0] > -0.5) & (c[:, 1] < 0.5))):
        L = room.leaves()
        om.save(om.from_leaves(L.codes[mask], L.depths[mask], L.log_odds[mask], 0.1), d / f"{name}.ot")
    return d


def octomerge(d, *args):
    return subprocess.run([sys.executable, "-m", "octomerge_jax", "merge", *map(str, args)],
                          capture_output=True, text=True, timeout=TIMEOUT_S)


def test_rule_max_and_sum_of_a_map_with_itself(d):
    a = om.load(d / "a.ot")
    for rule in ("sum", "max"):
        r = octomerge(d, d / "a.ot", d / "a.ot", d / f"{rule}.ot", "--refine", "none", "--rule", rule, "-q")
        assert r.returncode == 0, r.stderr
    ca = voxel_log_odds(a)
    lo, hi = np.float32(a.params.clamp_min_log_odds), np.float32(a.params.clamp_max_log_odds)
    want_sum = {k: float(np.clip(np.float32(v) + np.float32(v), lo, hi)) for k, v in ca.items()}
    got_sum, got_max = voxel_log_odds(om.load(d / "sum.ot")), voxel_log_odds(om.load(d / "max.ot"))
    assert got_max == ca  # max(l, l) = l
    assert got_sum == want_sum  # l + l, clamped
    assert sum(got_sum[k] != got_max[k] for k in ca) > len(ca) // 2


def test_interpolation_nearest_equals_library_transform_then_fuse(d):
    out, rep = d / "nearest.ot", d / "nearest.json"
    r = octomerge(d, d / "a.ot", d / "b.ot", out, "--refine", "none", "--xyz", "0.03", "-0.02", "0",
                  "--rpy", "0", "0", "0.2", "--interpolation", "nearest", "--report", rep, "-q")
    assert r.returncode == 0, r.stderr
    T = np.array(json.loads(rep.read_text())["T_1_2"], np.float64)
    a, b = om.load(d / "a.ot"), om.load(d / "b.ot")
    want = om.fuse(a, om.transform_map(b, T, "nearest", chunk_bricks=64))
    got = om.load(out)
    for field in ("codes", "depths", "log_odds"):
        np.testing.assert_array_equal(getattr(got.leaves(), field), getattr(want.leaves(), field))
    trilinear = om.fuse(a, om.transform_map(b, T, "trilinear", chunk_bricks=64))
    assert voxel_log_odds(trilinear) != voxel_log_odds(got)


SHIFT = (0.0, 0.05, 0.05)  # the guess: map 2's points half a voxel off map 1's grid


def _overlap_counts_from_error(d, method, need):
    """Counts of ``--overlap method`` from the no-overlap error: with ``need`` common points
    required (no more than either map's occupied points) a smaller overlap stops the run
    after the overlap step, before ICP."""
    cfg = d / f"need_{need}.toml"
    cfg.write_text(f"[registration]\nmin_overlap_points = {need}\n")
    r = octomerge(d, d / "a.ot", d / "b.ot", d / f"never_{method}.bt", "--overlap", method, "--config", cfg,
                  "--xyz", *SHIFT)
    assert r.returncode == 4, r.stderr
    m = re.search(r"only (\d+) points of map 1 and (\d+) of map 2", r.stderr)
    assert m, r.stderr
    return int(m.group(1)), int(m.group(2))


def _between(count, lower, upper):
    return lower <= count <= upper


def test_overlap_methods_select_what_they_name(d):
    a, b = om.load(d / "a.ot"), om.load(d / "b.ot")
    p1 = np.asarray(om.occupied_points(a), np.float64).reshape(-1, 3)
    p2 = np.asarray(om.occupied_points(b), np.float64).reshape(-1, 3)
    w = p2 + SHIFT  # map 2's points under the guess
    need = min(len(p1), len(p2))
    counts = {m: _overlap_counts_from_error(d, m, need) for m in ("bbox", "voxel")}

    # bbox (thesis Alg. 2, Appendix A.1): the points of map 2 strictly inside map 1's box, then
    # the points of map 1 strictly inside the box of that selection grown by the margin (1 m).
    # Counted with the boxes grown by -+ 1e-4 m: float32 ties at a border may go either way.
    def inside(p, lo, hi, eps):
        return np.all((p > lo - eps) & (p < hi + eps), axis=1)

    def bbox_counts(eps):
        m2 = inside(w, p1.min(0), p1.max(0), eps)
        m1 = inside(p1, w[m2].min(0) - 1.0, w[m2].max(0) + 1.0, eps)
        return int(m1.sum()), int(m2.sum())

    lower, upper = bbox_counts(-1e-4), bbox_counts(1e-4)
    for k in range(2):
        assert _between(counts["bbox"][k], lower[k], upper[k]), (counts, lower, upper)

    # voxel (radius 3 voxels = 0.3 m): points with a point of the other cloud that close
    def near(p, q, radius):
        dist, _ = cKDTree(q).query(p, k=1)
        return int((dist <= radius).sum())

    for k, (p, q) in enumerate(((p1, w), (w, p1))):
        assert _between(counts["voxel"][k], near(p, q, 0.3 - 1e-4), near(p, q, 0.3 + 1e-4)), counts
    # each method selects its own, non-empty, proper subsets
    assert counts["voxel"] != counts["bbox"]
    for method in ("bbox", "voxel"):
        assert 0 < counts[method][0] < len(p1) and 0 < counts[method][1] < len(p2), counts

    # none: every occupied point, in a run's --report (ICP on the whole clouds; the overlap step is the same
    # for every refinement that starts with ICP)
    rep = d / "none.json"
    r = octomerge(d, d / "a.ot", d / "b.ot", d / "none.bt", "--overlap", "none", "--refine", "icp", "--report", rep,
                  "-q", "--xyz", *SHIFT)
    assert r.returncode == 0, r.stderr
    c = json.loads(rep.read_text())["counts"]
    assert (c["overlap_1"], c["overlap_2"]) == (c["occupied_1"], c["occupied_2"]) == (len(p1), len(p2))


@pytest.mark.parametrize("flag", ["--rule", "--interpolation", "--overlap"])
def test_bad_option_value_is_usage_error(d, flag):
    r = octomerge(d, d / "a.ot", d / "b.ot", d / "bad.bt", flag, "bogus")
    assert r.returncode == 2
    assert f"argument {flag}: invalid choice: 'bogus'" in r.stderr
    assert not (d / "bad.bt").exists()
