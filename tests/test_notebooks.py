"""Execute every numbered example notebook top to bottom; any cell error fails the test. The
notebooks explain and print how far their results lie from closed forms; the physics claims they
show are asserted by the thematic tests (test_rod.py, test_separatrix.py, ...), not inside the
notebooks. Nothing is written back to the repository."""

from pathlib import Path

import nbclient
import nbformat
import pytest

NOTEBOOKS = Path(__file__).resolve().parent.parent / "notebooks"
PATHS = sorted(NOTEBOOKS.glob("[0-9][0-9]_*.ipynb"))


def test_notebooks_found():
    assert PATHS, f"no notebooks matching [0-9][0-9]_*.ipynb in {NOTEBOOKS}"


@pytest.mark.parametrize("path", PATHS, ids=[p.name for p in PATHS])
def test_notebooks_are_stored_without_outputs(path):
    """The `.ipynb` is the one source of each notebook (edit it in Jupyter); it is committed
    without outputs or execution counts (`nbstripout --keep-id notebooks/*.ipynb` strips them
    and keeps the cell ids), so diffs show only what was written. The docs site executes
    them to show their figures."""
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    for i, cell in enumerate(nb.cells):
        if cell.cell_type == "code":
            assert cell.outputs == [] and cell.execution_count is None, \
                f"{path.name} cell {i} holds outputs: run nbstripout --keep-id {path.name}"


# The notebooks whose time is running, not compiling (a posterior's sampling, a 192-run
# ensemble): their kernels compile as a user's do (conftest.py; the others 10-20 % faster with
# most of XLA's optimisations off, these 1.6-1.7x slower). Set for the kernel alone, which
# inherits the environment (not the `optimized` mark: this worker compiles nothing here, so
# it keeps its programs).
RUNNING = ("09_", "10_")


@pytest.mark.parametrize("path", PATHS, ids=[p.name for p in PATHS])
def test_notebook_executes(path, monkeypatch):
    # The inline backend renders every figure (so a broken label or mathtext fails here too)
    # without needing a display; the kernel inherits this environment.
    monkeypatch.setenv("MPLBACKEND", "module://matplotlib_inline.backend_inline")
    if path.name.startswith(RUNNING):
        monkeypatch.setenv("JAX_DISABLE_MOST_OPTIMIZATIONS", "0")
    nb = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(
        nb,
        kernel_name="python3",
        timeout=600,
        resources={"metadata": {"path": str(NOTEBOOKS)}},
        # Once the last cell has run, the kernel is ended at once, without its interpreter's
        # teardown (freeing its compiled programs: 0.7 s of the falling rod's 8.4 s).
        shutdown_kernel="immediate",
    )
    client.execute()  # raises CellExecutionError on the first failing cell; `nb` stays in memory
