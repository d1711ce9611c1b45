"""The notebooks run top to bottom without errors and show images (at a small size).

Needs nbformat, nbclient and ipykernel (the `test` extra); a missing package fails the
test with a message rather than skipping it.
"""

import importlib.util
import pathlib

import pytest

NOTEBOOKS = pathlib.Path(__file__).resolve().parent.parent / "notebooks"
SIZE = "24"  # JAXISO_NB_SIZE for the kernel: tiny images, the run is compile-bound


def _require(*modules):
    missing = [m for m in modules if importlib.util.find_spec(m) is None]
    if missing:
        pytest.fail(f"notebook tests need {', '.join(missing)}: "
                    f'pip install -e ".[test]" (or pip install {" ".join(missing)})',
                    pytrace=False)


def _images(cell):
    return sum("image/png" in out.get("data", {}) for out in cell.get("outputs", []))


# the fewest image outputs each notebook shows (04 draws one more with the shared fox)
MIN_IMAGES = {"01_implicits.ipynb": 9, "02_volumes.ipynb": 9, "03_tet_meshes.ipynb": 9,
              "04_neural_implicits.ipynb": 4}


@pytest.mark.parametrize("name", sorted(MIN_IMAGES))
def test_notebook_runs(name, monkeypatch):
    _require("nbformat", "nbclient", "ipykernel")
    import nbformat
    from nbclient import NotebookClient
    from nbclient.exceptions import CellExecutionError

    # the kernel inherits this process's environment; "python3" is ipykernel's own spec,
    # which runs this interpreter (the one jaxiso is installed in)
    monkeypatch.setenv("JAXISO_NB_SIZE", SIZE)
    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    client = NotebookClient(nb, timeout=600, kernel_name="python3",
                            resources={"metadata": {"path": str(NOTEBOOKS)}})
    try:
        client.execute()
    except CellExecutionError as e:
        pytest.fail(f"{name} failed:\n{e}", pytrace=False)

    code = [c for c in nb.cells if c.cell_type == "code"]
    errors = [o for c in code for o in c.get("outputs", []) if o.output_type == "error"]
    assert not errors, errors
    assert all(c.get("execution_count") for c in code), "a code cell did not run"
    n_images = sum(_images(c) for c in code)
    assert n_images >= MIN_IMAGES[name], f"only {n_images} image outputs"
