"""Execute every notebook in notebooks/ top to bottom; any failing cell fails the test.

The notebooks read their size from ``TORCHMETAL_NB_SIZE`` (small here) and write their files to
``TORCHMETAL_NB_OUT``; they run in a temporary directory with the ``python3`` kernel of the
interpreter running pytest. Outputs are not stored in git: the committed notebooks must have none.
"""

import os
import re
import sys
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))
SIZE = os.environ.get("TORCHMETAL_TEST_NB_SIZE", "64")
# one intra-op thread per kernel: on a shared 2-core machine that is faster and far steadier
THREADS = os.environ.get("TORCHMETAL_TEST_THREADS", "1")
CELL_TIMEOUT = 300


def test_notebooks_found():
    names = [p.name for p in NOTEBOOKS]
    assert names[:4] == ["01_quickstart.ipynb", "02_phong_fit.ipynb", "03_flakes.ipynb", "04_onnx.ipynb"]
    assert [int(n[:2]) for n in names] == list(range(1, len(names) + 1)), names


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_is_stored_without_outputs(path):
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    for i, cell in enumerate(nb.cells):
        if cell.cell_type == "code":
            assert not cell.outputs and cell.execution_count is None, f"{path.name} cell {i}: outputs stored in git"
    assert nb.cells[0].cell_type == "markdown" and nb.cells[0].source.startswith("# ")


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_runs(path, tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHMETAL_NB_SIZE", SIZE)
    monkeypatch.setenv("TORCHMETAL_NB_OUT", str(tmp_path / "out"))
    monkeypatch.setenv("MPLBACKEND", "module://matplotlib_inline.backend_inline")
    monkeypatch.setenv("OMP_NUM_THREADS", THREADS)
    monkeypatch.setenv("MKL_NUM_THREADS", THREADS)
    # the kernel is a child of this interpreter: make sure it imports the same torchmetal
    root = str(Path(__file__).resolve().parents[1])
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([root, os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))
    nb = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(
        nb,
        timeout=CELL_TIMEOUT,
        kernel_name="python3",
        resources={"metadata": {"path": str(tmp_path)}},
        allow_errors=False,
    )
    # use this interpreter's kernel, whatever kernelspecs the machine has installed
    client.kernel_manager_class = _LocalKernelManager
    try:
        client.execute()
    except nbclient.exceptions.CellExecutionError as e:
        text = re.sub(r"\x1b\[[0-9;]*m", "", str(e))  # no terminal colours in the report
        pytest.fail(f"{path.name}: a cell failed\n{text[-3000:]}")


def _local_kernel_manager():
    from jupyter_client.manager import KernelManager

    class LocalKernelManager(KernelManager):
        """Always start ipykernel with ``sys.executable`` (the venv running the tests)."""

        def format_kernel_cmd(self, extra_arguments=None):
            return [sys.executable, "-m", "ipykernel_launcher", "-f", self.connection_file]

    return LocalKernelManager


_LocalKernelManager = _local_kernel_manager()
