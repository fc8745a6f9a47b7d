"""Execute notebooks in place so that they are committed with their outputs:
``python notebooks/execute.py notebooks/*.ipynb``.

Each notebook runs top to bottom in a fresh kernel (cwd ``notebooks/``); its PNG figures are
re-encoded as 256-colour palette PNGs (a few tens of KB each) and the SHA-256 of its code
cells is stored in ``metadata.octomerge_jax.code_sha256``, which ``tests/test_notebooks.py``
compares with the committed code so stale outputs fail the tests. Needs nbclient, nbformat,
ipykernel and Pillow (the ``test`` extra).
"""

from __future__ import annotations

import argparse
import base64
import hashlib
import io
import os
import sys
import tempfile
from pathlib import Path


def code_sha256(nb) -> str:
    """SHA-256 over the code cells' sources, in order (what an execution depends on)."""
    h = hashlib.sha256()
    for cell in nb.cells:
        if cell.cell_type == "code":
            h.update(cell.source.encode())
            h.update(b"\0")
    return h.hexdigest()


def compress_png(data_b64: str) -> str:
    """A PNG (base64) re-encoded with a 256-colour palette, optimised; the original when that
    is not smaller."""
    from PIL import Image

    raw = base64.b64decode(data_b64)
    img = Image.open(io.BytesIO(raw)).convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT)
    out = io.BytesIO()
    img.save(out, format="PNG", optimize=True)
    return base64.b64encode(out.getvalue()).decode() if out.tell() < len(raw) else data_b64


def execute(path: Path, timeout_s: int = 1200) -> int:
    """Run ``path`` and write it back with outputs; returns its size in bytes."""
    import nbclient
    import nbformat

    nb = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(nb, timeout=timeout_s, kernel_name="python3",
                                     resources={"metadata": {"path": str(path.parent)}})
    client.execute()
    for cell in nb.cells:
        for out in cell.get("outputs", []):
            if "image/png" in out.get("data", {}):
                out["data"]["image/png"] = compress_png(out["data"]["image/png"])
    nb.metadata["octomerge_jax"] = {"code_sha256": code_sha256(nb)}
    mode = path.stat().st_mode & 0o777
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            nbformat.write(nb, f)
        os.chmod(tmp, mode)  # keep the notebook's permissions (mkstemp makes 0600)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path.stat().st_size


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("notebooks", type=Path, nargs="+")
    args = p.parse_args(argv)
    for path in args.notebooks:
        size = execute(path)
        print(f"{path}: {size / 1024:.0f} KiB", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
