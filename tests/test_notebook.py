"""examples/quickstart.ipynb runs from top to bottom (synthetic flame, then a real ScalarFlow
frame where the data is there): reconstruct, score, a novel view, exports. Skipped, with the
reason, only where no Jupyter kernel can start."""

from __future__ import annotations

import pytest

from tests.helpers import REPO, repo_env

NOTEBOOK = REPO / "examples" / "quickstart.ipynb"


@pytest.mark.e2e
def test_the_quickstart_notebook_runs(tmp_path, monkeypatch):
    nbformat = pytest.importorskip("nbformat", reason="the dev extra's nbformat is not installed")
    nbclient = pytest.importorskip("nbclient", reason="the dev extra's nbclient is not installed")
    from jupyter_client.kernelspec import NoSuchKernel

    for key, value in repo_env().items():  # the kernel imports flamerecon from this checkout
        monkeypatch.setenv(key, value)
    notebook = nbformat.read(NOTEBOOK, as_version=4)
    client = nbclient.NotebookClient(notebook, timeout=300, kernel_name="python3",
                                     resources={"metadata": {"path": str(tmp_path)}})
    try:
        client.execute()
    except NoSuchKernel as err:
        pytest.skip(f"no Jupyter kernel can start here: {err}")
    printed = "".join(o.get("text", "") for c in notebook.cells if c.cell_type == "code" for o in c.outputs)
    assert "held-out cam04: PSNR" in printed
    pictures = [o for c in notebook.cells if c.cell_type == "code" for o in c.outputs if "image/png" in o.get("data", {})]
    assert len(pictures) >= 3  # the held-out view, the novel views and the slices, inline
    assert "novel views (3, " in printed
    assert "'synthetic.vti', 'synthetic.ply', 'synthetic.obj'" in printed
    if (REPO.parent / "shared" / "data" / "scalarflow_real").is_dir():
        assert "'scalarflow_frame25.vti'" in printed
