"""The main job (README quick start, step 1) runs and prints every catalogue surface."""

import subprocess
import sys

import jaxiso as ji


def test_demo_runs_and_lists_catalogue():
    out = subprocess.run([sys.executable, "-m", "jaxiso.cli", "demo", "--names", "sphere",
                          "barth_sextic"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "barth_sextic" in out.stdout and "sphere" in out.stdout
    assert "certainly true" in out.stdout


def test_catalogue_lookup():
    assert "barth_sextic" in ji.surfaces.names()
    try:
        ji.surfaces.get("nope")
    except KeyError as e:
        assert "known" in str(e)
    else:
        raise AssertionError("unknown surface did not raise")
