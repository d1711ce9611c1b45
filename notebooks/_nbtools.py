"""The notebooks' generators make_01.py .. make_04.py share this: a notebook built cell by
cell from dedented text, the set-up cell with the image-size parameter, the code of the
helper functions the notebooks define, and storing the notebook executed.

Regenerate every stored notebook (build from its make_*.py, execute at the notebook's
own image size, keep the outputs):

    python notebooks/_nbtools.py --all          # or: python notebooks/_nbtools.py 01 03

A stored notebook records the SHA-256 of its cells' sources in its metadata
(``jaxiso.cells_sha256``); tests/test_notebooks.py rebuilds the cells from make_*.py and
fails when they differ, i.e. when a generator changed and the notebook was not rerun.
The generators import this file as ``_nbtools`` (run from this folder or with it on
``sys.path``).
"""

import argparse
import base64
import hashlib
import io
import json
import os
import pathlib
import runpy
import sys
import textwrap
import time

import nbformat
from nbformat.v4 import new_code_cell, new_markdown_cell, new_notebook

HERE = pathlib.Path(__file__).resolve().parent  # the notebooks and their generators

# the notebook metadata every generated notebook carries
METADATA = {
    "kernelspec": {"name": "python3", "display_name": "Python 3", "language": "python"},
    "language_info": {"name": "python"},
}

# Helper functions defined in the notebooks' second code cell (see `helpers`)
ROW = '''
def row(*images, gap=4):
    """Images side by side (white gaps): an `ji.Image`, so it shows inline."""
    h = max(im.shape[0] for im in images)
    parts = []
    for i, im in enumerate(images):
        im = np.asarray(im, np.float32)
        if i:
            parts.append(np.ones((h, gap, 3), np.float32))
        pad = np.ones((h - im.shape[0], im.shape[1], 3), np.float32)
        parts.append(np.concatenate([im, pad], axis=0))
    return ji.Image(np.concatenate(parts, axis=1))
'''

TIMED = '''
def timed(fn, *args, **kwargs):
    """(result, seconds); waits for the device."""
    t = time.perf_counter()
    out = jax.block_until_ready(fn(*args, **kwargs))
    return out, time.perf_counter() - t
'''


def clean(text):
    """Cell text as written in a generator: dedented, without leading/trailing blank lines."""
    return textwrap.dedent(text).strip()


def heat(what):
    """Code of heat(values, vmax), whose docstring calls the values a per-pixel `what`."""
    return f'''
def heat(values, vmax):
    """A per-pixel {what} as an image: white (0) to dark red (>= vmax)."""
    v = np.clip(np.asarray(values, np.float32) / vmax, 0.0, 1.0)[..., None]
    return ji.Image((1.0 - v) + v * np.array([0.6, 0.05, 0.05], np.float32))
'''


def helpers(*functions):
    """Code of several top-level functions, two blank lines apart."""
    return "\n\n\n".join(clean(f) for f in functions)


def setup(imports, size_default, more="", note=""):
    """Code of the first code cell: `imports`, then SIZE, the image edge, from
    JAXISO_NB_SIZE (the test suite runs the notebooks small) else `size_default`, then the
    `more` lines, then a line printing the versions, the device and SIZE, and `note`."""
    lines = [clean(imports), "",
             f'SIZE = int(os.environ.get("JAXISO_NB_SIZE", "{size_default}"))']
    if more:
        lines.append(clean(more))
    lines.append('print(f"jaxiso {ji.__version__}, jax {jax.__version__} on '
                 '{jax.devices()[0].platform}, "')
    lines.append('      f"{SIZE}x{SIZE} images' + note + '")')
    return "\n".join(lines)


class Notebook:
    """The cells of notebooks/<name> in the order md / code add them."""

    def __init__(self, name):
        self.path = HERE / name
        self.cells = []

    def md(self, text):
        self.cells.append(new_markdown_cell(clean(text)))

    def code(self, text):
        self.cells.append(new_code_cell(clean(text)))

    def notebook(self):
        """The validated notebook. Cells get ids by position (nbformat's are random), so
        building an unchanged generator twice gives the same notebook."""
        for i, cell in enumerate(self.cells):
            cell["id"] = f"cell-{i:03d}"
        nb = new_notebook(cells=self.cells, metadata=dict(METADATA))
        nbformat.validate(nb)
        return nb


def generators():
    """The make_NN.py files, in order."""
    return sorted(HERE.glob("make_[0-9][0-9].py"))


def build(make):
    """(path of the stored notebook, the notebook without outputs) from generator `make`;
    runs the generator as a module, so it writes nothing."""
    sys.path.insert(0, str(HERE))
    try:
        book = runpy.run_path(str(make), run_name="_generator")["NOTEBOOK"]
    finally:
        sys.path.remove(str(HERE))
    return book.path, book.notebook()


def cells_sha256(nb):
    """SHA-256 of the cells' kinds and sources: what was executed, not what it printed."""
    cells = [[c["cell_type"], c["source"]] for c in nb["cells"]]
    return hashlib.sha256(json.dumps(cells).encode()).hexdigest()


def small_png(data, colors=128):
    """A base64 PNG re-encoded with a palette of `colors` (shaded renders lose nothing
    visible; the stored notebooks shrink severalfold)."""
    from PIL import Image

    img = Image.open(io.BytesIO(base64.b64decode(data))).convert("RGB")
    buf = io.BytesIO()
    img.quantize(colors, dither=Image.Dither.NONE).save(buf, format="PNG", optimize=True)
    return base64.b64encode(buf.getvalue()).decode()


def execute(nb, size=None, timeout=1800):
    """Runs `nb` in a fresh kernel in this folder (raises on the first failing cell); the
    kernel sees JAXISO_NB_SIZE=`size`, or no such variable when `size` is None."""
    from nbclient import NotebookClient

    env = dict(os.environ)
    env.pop("JAXISO_NB_SIZE", None)
    if size is not None:
        env["JAXISO_NB_SIZE"] = str(size)
    client = NotebookClient(nb, timeout=timeout, kernel_name="python3",
                            resources={"metadata": {"path": str(HERE)}})
    client.execute(env=env)
    return nb


def regenerate(make):
    """Builds, executes (at the notebook's own image size) and stores the notebook of
    generator `make` (a path), with small images and the cells' hash in its metadata."""
    make = pathlib.Path(make)
    path, nb = build(make)
    t0 = time.perf_counter()
    execute(nb)
    for cell in nb.cells:
        for out in cell.get("outputs", []):
            if "image/png" in out.get("data", {}):
                out["data"]["image/png"] = small_png(out["data"]["image/png"])
    nb.metadata["jaxiso"] = {"cells_sha256": cells_sha256(nb), "generator": make.name}
    nbformat.validate(nb)
    nbformat.write(nb, path)
    print(f"{path.name}: executed in {time.perf_counter() - t0:.0f} s, "
          f"{path.stat().st_size / 1e3:.0f} kB")


def main(argv=None):
    parser = argparse.ArgumentParser(description="regenerate the stored notebooks")
    parser.add_argument("which", nargs="*", help="notebook numbers, e.g. 01 03")
    parser.add_argument("--all", action="store_true", help="every notebook")
    args = parser.parse_args(argv)
    chosen = [m for m in generators() if args.all or m.stem[5:] in args.which]
    if not chosen:
        parser.error("name notebook numbers (01 .. 04) or --all")
    for make in chosen:
        regenerate(make)


if __name__ == "__main__":
    main()
