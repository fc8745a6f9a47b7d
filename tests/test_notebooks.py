"""Execute the notebooks (nbclient, small settings): every cell must run and their assertions
hold. Needs nbclient, nbformat and ipykernel (the test extra)."""

from __future__ import annotations

from pathlib import Path

import pytest

NOTEBOOKS = Path(__file__).resolve().parent.parent / "notebooks"


# 02 runs 15 registrations (45-58 s on 2 cores) and 03 gradient tuning (~33 s): in the slow run;
# the default run keeps the main workflow (01); Table 7.1 / 7.2 rows are tested in
# test_registration_icp / _overlap, dense alignment and its gradients in test_dense
@pytest.mark.parametrize("name", ["01_merge_two_maps.ipynb",
                                  pytest.param("02_thesis_tables.ipynb", marks=pytest.mark.slow),
                                  pytest.param("03_gradient_transform_tuning.ipynb", marks=pytest.mark.slow),
                                  # 04 registers every overlapping pair of four robots' maps (ICP): minutes
                                  pytest.param("04_many_robots.ipynb", marks=pytest.mark.slow)])
def test_notebook_runs(name, monkeypatch):
    from octomerge_jax.cli.cache import worker_env

    for key, value in worker_env().items():  # the kernel loads what the run compiled (tests/conftest.py)
        monkeypatch.setenv(key, value)
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    pytest.importorskip("ipykernel")
    path = NOTEBOOKS / name
    nb = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(nb, timeout=600, kernel_name="python3",
                                     resources={"metadata": {"path": str(NOTEBOOKS)}})
    client.execute()
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
              if o.get("output_type") == "error"]
    assert not errors
    images = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
              if "image/png" in o.get("data", {})]
    if name.startswith("01"):
        assert len(images) >= 3  # overlap, merged map, ICP convergence figures
    if name.startswith("04"):
        assert len(images) >= 2  # the pose graph over the footprints, the merged map


def _committed():
    return sorted(NOTEBOOKS.glob("*.ipynb"))


@pytest.mark.parametrize("path", _committed(), ids=lambda p: p.name)
def test_committed_notebook_has_the_outputs_of_its_code(path):
    """A committed notebook was executed top to bottom by ``notebooks/execute.py`` with the
    code it holds now (no stale outputs), shows its figures, and stays small enough to read on
    GitHub."""
    import importlib.util

    nbformat = pytest.importorskip("nbformat")
    spec = importlib.util.spec_from_file_location("execute", NOTEBOOKS / "execute.py")
    execute = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(execute)
    nb = nbformat.read(path, as_version=4)
    stored = nb.metadata.get("octomerge_jax", {}).get("code_sha256")
    assert stored == execute.code_sha256(nb), (
        f"{path.name}: code changed since it was executed; run python notebooks/execute.py {path}")
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert [c.execution_count for c in code] == list(range(1, len(code) + 1)), "not run top to bottom"
    outputs = [o for c in code for o in c.outputs]
    assert not [o for o in outputs if o.get("output_type") == "error"]
    assert outputs, "no outputs"
    if path.name.startswith(("01", "04")):
        assert any("image/png" in o.get("data", {}) for o in outputs), "no figure"
    assert path.stat().st_size < 600_000
    for c in code:  # public names only
        assert "sys.path" not in c.source
        assert not any(part.startswith("_") for line in c.source.splitlines()
                       if line.lstrip().startswith(("import ", "from ")) for part in
                       line.replace(",", " ").replace(".", " ").split() if part != "__future__")
