"""What the notebook generators make_01.py .. make_03.py share: a notebook built cell by
cell from dedented text, the set-up cell with the image-size parameter, the code of the
helper functions the notebooks define, and writing the .ipynb (validated, no outputs).

The generators run as scripts from this folder, so they import it as ``_nbtools``.
"""

import pathlib
import textwrap

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
    """The cells of notebooks/<name> in the order md / code add them; write() stores it."""

    def __init__(self, name):
        self.path = HERE / name
        self.cells = []

    def md(self, text):
        self.cells.append(new_markdown_cell(clean(text)))

    def code(self, text):
        self.cells.append(new_code_cell(clean(text)))

    def write(self):
        """Validates and writes the notebook. Cells get ids by position (nbformat's are
        random), so regenerating an unchanged notebook changes nothing."""
        for i, cell in enumerate(self.cells):
            cell["id"] = f"cell-{i:03d}"
        nb = new_notebook(cells=self.cells, metadata=METADATA)
        nbformat.validate(nb)
        nbformat.write(nb, self.path)
        print(f"wrote {self.path} ({len(self.cells)} cells)")
