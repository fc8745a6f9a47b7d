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
def test_notebook_runs(name):
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
