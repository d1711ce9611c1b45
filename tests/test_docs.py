"""The documentation runs: every ```python block of README.md and docs/*.md.

Each page's blocks run in order in one namespace (a page reads as one session), in a
temporary working directory (examples write PNGs). The examples use small images so the
suite stays fast; the time goes to compilation.

A block may opt out with a first line ``# docs-test: skip (<reason>)``. Only two reasons
are accepted, and the test fails on any other: ``shell`` (the block shows commands, not
Python) and ``data`` (it needs a file the repository does not ship, e.g. a user's volume).
Blocks in other languages (```bash, ```text) are not run.

Also checked: README.md stays a front door (at most 180 lines), every relative link of
README.md and docs/*.md points to a file that exists, and the contact sheet script runs
at a tiny size.
"""

import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
SKIP = re.compile(r"#\s*docs-test:\s*skip\s*\((?P<why>[^)]*)\)")
REASONS = ("shell", "data")
FENCE = re.compile(r"^```(?P<lang>\w*)\n(?P<code>.*?)^```", re.S | re.M)


def blocks(page: pathlib.Path):
    """(line number, code) of each ```python block of the page, in order."""
    text = page.read_text()
    for m in FENCE.finditer(text):
        if m.group("lang") == "python":
            yield text.count("\n", 0, m.start()) + 2, m.group("code")


def _name(page):
    return str(page.relative_to(ROOT))


@pytest.mark.parametrize("page", PAGES, ids=_name)
def test_page_code_runs(page, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": f"docs_{page.stem}"}
    ran = 0
    for line, code in blocks(page):
        first = code.lstrip().splitlines()[0] if code.strip() else ""
        skip = SKIP.match(first)
        if skip:
            assert skip.group("why").split(":")[0].strip() in REASONS, (
                f"{_name(page)}:{line}: a block may skip only for {REASONS}, "
                f"not {skip.group('why')!r}")
            continue
        try:
            exec(compile(code, f"{_name(page)}:{line}", "exec"), namespace)
        except Exception as e:
            raise AssertionError(f"{_name(page)}: the block at line {line} fails: "
                                 f"{type(e).__name__}: {e}") from e
        ran += 1
    if not ran:
        pytest.skip(f"{_name(page)} has no python block")


def test_readme_is_short():
    lines = (ROOT / "README.md").read_text().count("\n")
    assert lines <= 180, f"README.md has {lines} lines; move detail into docs/"


LINK = re.compile(r"\]\((?P<target>[^)#\s]+)(?:#[^)]*)?\)")


@pytest.mark.parametrize("page", PAGES, ids=_name)
def test_relative_links_exist(page):
    missing = [m.group("target") for m in LINK.finditer(page.read_text())
               if "://" not in m.group("target")
               and not (page.parent / m.group("target")).exists()]
    assert not missing, f"{_name(page)} links to missing files: {missing}"


# ~50 s on 2 cores (four scene kinds compiled): run when the picture is regenerated
@pytest.mark.heavy
def test_contact_sheet_script_runs(tmp_path, monkeypatch):
    """At 24 px a panel; without the shared fox (its fallback network is built here)."""
    import importlib.util

    from PIL import Image

    monkeypatch.setenv("JAXISO_NEURAL_DATA", str(tmp_path))
    spec = importlib.util.spec_from_file_location(
        "make_contact_sheet", ROOT / "examples" / "make_contact_sheet.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    out = tmp_path / "sheet.png"
    assert module.main(["--size", "24", "--out", str(out)]) == 0
    img = Image.open(out)
    assert img.size[0] == 4 * 24 and img.size[1] > 24


def test_layout_lists_every_module():
    """docs/layout.md names each module of jaxiso/ under its package's heading (a
    subpackage's __init__.py only gathers its public names and is not listed)."""
    text = (ROOT / "docs" / "layout.md").read_text()
    sections = dict(re.findall(r"^## `(jaxiso/[\w/]*)`[^\n]*\n(.*?)(?=^## |\Z)", text,
                               re.S | re.M))
    missing = []
    for path in sorted((ROOT / "jaxiso").rglob("*.py")):
        if path.name == "__init__.py" and path.parent != ROOT / "jaxiso":
            continue
        package = path.parent.relative_to(ROOT).as_posix() + "/"
        if f"`{path.name}`" not in sections.get(package, ""):
            missing.append(path.relative_to(ROOT).as_posix())
    assert not missing, f"docs/layout.md does not list: {missing}"
