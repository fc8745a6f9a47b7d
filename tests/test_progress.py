"""Progress bars: drawn on a terminal, never when stderr is piped or with --quiet."""

from __future__ import annotations

import io
import sys

import numpy as np

import octomerge_jax as om
from octomerge_jax.cli import main
from octomerge_jax.cli.progress import Progress, StageBar, show_bars
from octomerge_jax.pipeline import Timings


class FakeTty(io.StringIO):
    def isatty(self):
        return True


def test_show_bars_follows_the_stream():
    assert show_bars(stream=FakeTty()) and not show_bars(quiet=True, stream=FakeTty())
    assert not show_bars(stream=io.StringIO())


def test_stage_bar_follows_pipeline_stages(monkeypatch):
    err = FakeTty()
    monkeypatch.setattr(sys, "stderr", err)
    bar = StageBar(True, "merge")
    t = Timings()
    with bar.watch():
        with t.stage("correlation"):
            assert "correlation" in err.getvalue()
        with t.stage("icp"):
            pass
    with t.stage("fuse"):  # not watched any more
        pass
    bar.close()
    assert "merge [00:00] 2 stages done" in err.getvalue() and "fuse" not in err.getvalue()
    p = Progress(3, True, desc="inserting", unit="scan")
    p.update(n=3)
    p.close()
    assert "inserting: 100%" in err.getvalue() and "3/3" in err.getvalue()


def _export(tmp_path, *flags):
    om.save(om.example_map(), tmp_path / "room.bt")
    return main(["export", str(tmp_path / "room.bt"), str(tmp_path / "room.pcd"), *flags])


def test_cli_bar_only_on_a_terminal(tmp_path, monkeypatch, capsys):
    assert _export(tmp_path) == 0  # captured stderr: not a terminal
    assert capsys.readouterr().err == ""
    err = FakeTty()
    monkeypatch.setattr(sys, "stderr", err)
    assert _export(tmp_path, "--force") == 0
    assert "export: 100%" in err.getvalue() and "2/2" in err.getvalue()
    err.seek(0), err.truncate()
    assert _export(tmp_path, "--quiet", "--force") == 0
    assert err.getvalue() == ""
    assert np.isfinite(om.load(tmp_path / "room.bt").resolution)
