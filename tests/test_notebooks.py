"""The stored notebooks are current and executed, and they still run.

* Stale (cheap, every notebook): the cells rebuilt from notebooks/make_NN.py must equal the
  stored cells, whose hash the regeneration (``python notebooks/_nbtools.py --all``)
  recorded in the metadata when it executed them; every stored code cell has run, without
  errors, and the notebook shows its images.
* Runs: each notebook executes top to bottom at a small image size (JAXISO_NB_SIZE=24).
  This is compile-bound (one to three minutes each on 2 cores), so by default only the
  cheapest one runs and the others are marked heavy.

Needs nbformat, nbclient and ipykernel (the `test` extra); a missing package fails the
test with a message rather than skipping it.
"""

import importlib.util
import pathlib
import sys

import pytest

NOTEBOOKS = pathlib.Path(__file__).resolve().parent.parent / "notebooks"
SIZE = 24  # JAXISO_NB_SIZE for the kernel: tiny images, the run is compile-bound
REGENERATE = "regenerate it: python notebooks/_nbtools.py --all (or make_NN.py)"

# the fewest image outputs each notebook shows (04 draws one more with the shared fox)
MIN_IMAGES = {"01_implicits.ipynb": 9, "02_volumes.ipynb": 9, "03_tet_meshes.ipynb": 9,
              "04_neural_implicits.ipynb": 4}
GENERATORS = {f"make_{name[:2]}.py": name for name in MIN_IMAGES}
CHEAP = {"03_tet_meshes.ipynb"}  # executed by default; the others are heavy


def _require(*modules):
    missing = [m for m in modules if importlib.util.find_spec(m) is None]
    if missing:
        pytest.fail(f"notebook tests need {', '.join(missing)}: "
                    f'pip install -e ".[test]" (or pip install {" ".join(missing)})',
                    pytrace=False)


@pytest.fixture(scope="module")
def nbtools():
    """notebooks/_nbtools.py as a module (the generators import it by that name)."""
    _require("nbformat", "nbclient", "ipykernel", "PIL")
    sys.path.insert(0, str(NOTEBOOKS))
    try:
        import _nbtools
    finally:
        sys.path.remove(str(NOTEBOOKS))
    return _nbtools


def _images(cell):
    return sum("image/png" in out.get("data", {}) for out in cell.get("outputs", []))


def _code(nb):
    return [c for c in nb.cells if c.cell_type == "code"]


def _check_executed(nb, name):
    """Every code cell ran, none failed, and at least MIN_IMAGES[name] images show."""
    errors = [o for c in _code(nb) for o in c.get("outputs", []) if o.output_type == "error"]
    assert not errors, f"{name}: {errors}"
    unrun = [i for i, c in enumerate(nb.cells) if c.cell_type == "code"
             and not c.get("execution_count")]
    assert not unrun, f"{name}: cells {unrun} did not run"
    n_images = sum(_images(c) for c in _code(nb))
    assert n_images >= MIN_IMAGES[name], f"{name}: only {n_images} image outputs"


def test_every_generator_has_its_notebook(nbtools):
    assert {m.name for m in nbtools.generators()} == set(GENERATORS)
    for make in nbtools.generators():
        path, _ = nbtools.build(make)
        assert path.name == GENERATORS[make.name]


@pytest.mark.parametrize("make", sorted(GENERATORS))
def test_stored_notebook_is_current_and_executed(make, nbtools):
    import nbformat

    path, built = nbtools.build(NOTEBOOKS / make)
    stored = nbformat.read(path, as_version=4)
    recorded = stored.metadata.get("jaxiso", {}).get("cells_sha256")
    assert recorded, f"{path.name} was stored unexecuted; {REGENERATE}"
    assert nbtools.cells_sha256(stored) == recorded, \
        f"{path.name}: cells edited after it was executed; {REGENERATE}"
    assert nbtools.cells_sha256(built) == recorded, \
        f"{path.name} is stale against {make}; {REGENERATE}"
    _check_executed(stored, path.name)


def test_stored_images_are_small():
    total = sum(p.stat().st_size for p in NOTEBOOKS.glob("*.ipynb"))
    assert total < 1_500_000, f"the stored notebooks hold {total / 1e6:.1f} MB"


@pytest.mark.parametrize("make", [m if GENERATORS[m] in CHEAP else pytest.param(
    m, marks=pytest.mark.heavy) for m in sorted(GENERATORS)])
def test_notebook_runs(make, nbtools):
    from nbclient.exceptions import CellExecutionError

    path, nb = nbtools.build(NOTEBOOKS / make)
    try:
        nbtools.execute(nb, size=SIZE, timeout=600)
    except CellExecutionError as e:
        pytest.fail(f"{path.name} failed:\n{e}", pytrace=False)
    _check_executed(nb, path.name)
