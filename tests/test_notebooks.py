"""The committed notebooks (docs/notebooks, built by docs/notebooks/build.py): every one has outputs,
no error cell, and was executed on the current sources (a digest of the library, data_gen and the
shipped weights); under `slow`, each is executed again top to bottom (nbclient) and must not fail."""
from __future__ import annotations

from pathlib import Path

import pytest

import jaxdenoise

NB_DIR = Path(__file__).resolve().parents[1] / "docs" / "notebooks"
NAMES = ("quickstart", "error_vs_time", "train_your_own", "stability_and_leave_out")


def _builder():
    import importlib.util

    spec = importlib.util.spec_from_file_location("nb_build", NB_DIR / "build.py")
    build = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(build)
    return build


@pytest.mark.parametrize("name", NAMES)
def test_committed_notebook_is_executed_and_current(name):
    """Executed (outputs, no error cell) with the sources of today: the digest of jaxdenoise,
    data_gen and the shipped weights it ran with equals the current one (`build.sources_sha256`;
    any change there means ``python docs/notebooks/build.py``)."""
    nbformat = pytest.importorskip("nbformat")
    nb = nbformat.read(NB_DIR / f"{name}.ipynb", as_version=4)
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert code and all(c.get("execution_count") for c in code), "a code cell was never executed"
    assert all(o.get("output_type") != "error" for c in code for o in c.get("outputs", [])), "an error cell"
    assert any(c.get("outputs") for c in code)
    meta = nb.metadata["jaxdenoise"]
    assert meta["version"] == jaxdenoise.__version__
    assert meta.get("sources_sha256") == _builder().sources_sha256(), \
        f"{name}.ipynb ran on other sources: python docs/notebooks/build.py {name}"


def test_notebooks_are_the_builder_sources():
    """The committed cells are exactly build.py's sources (edit build.py, then rebuild)."""
    nbformat = pytest.importorskip("nbformat")
    build = _builder()
    for name in NAMES:
        nb = nbformat.read(NB_DIR / f"{name}.ipynb", as_version=4)
        assert [c.source for c in nb.cells] == [src for _, src in build.NOTEBOOKS[name]]


@pytest.mark.slow
@pytest.mark.parametrize("name", NAMES)
def test_notebook_runs_top_to_bottom(name):
    nbformat = pytest.importorskip("nbformat")
    from nbclient import NotebookClient

    nb = nbformat.read(NB_DIR / f"{name}.ipynb", as_version=4)
    NotebookClient(nb, timeout=900, kernel_name="python3", resources={"metadata": {"path": str(NB_DIR)}}).execute()
