"""`ji.enable_cache`: compiled programs land in the folder and a second process reads them
back; the command line keeps them unless told `--no-cache`. Each case runs fresh Python
processes, so the suite's own JAX configuration is left alone."""

import os
import subprocess
import sys

import jaxiso as ji

# a process that enables the cache in argv[1], compiles one small program and prints its
# value and how many programs it found in the cache
PROGRAM = """
import sys
import jax
import jax.numpy as jnp
import jaxiso as ji

hits = []
jax.monitoring.register_event_listener(
    lambda name, **kw: hits.append(name) if name.endswith("/cache_hits") else None)
print(ji.enable_cache(sys.argv[1]))
f = jax.jit(lambda x: jnp.sin(x) * 3.0 + x)
print(float(f(jnp.float32(0.5))), len(hits))
"""


def _run(*args, env=None):
    out = subprocess.run([sys.executable, *args], capture_output=True, text=True,
                         timeout=300, env=env)
    assert out.returncode == 0, out.stderr
    return out.stdout.split()


def _entries(folder):
    return [name for name in os.listdir(folder) if not name.startswith(".")]


def test_default_folder_follows_the_environment():
    assert ji._cache.default_cache_dir({"JAXISO_CACHE_DIR": "/x/y"}) == "/x/y"
    assert ji._cache.default_cache_dir({"XDG_CACHE_HOME": "/c"}) == "/c/jaxiso/xla"
    home = os.path.expanduser("~")
    assert ji._cache.default_cache_dir({}) == os.path.join(home, ".cache", "jaxiso", "xla")


def test_a_second_process_reads_the_first_ones_programs(tmp_path):
    folder = tmp_path / "new" / "cache"           # made by enable_cache
    path, value, hits = _run("-c", PROGRAM, str(folder))
    assert path == str(folder) and int(hits) == 0
    assert abs(float(value) - 1.938276) < 1e-5      # 3 sin(0.5) + 0.5
    assert _entries(folder), "nothing was written to the cache"
    _, again, hits = _run("-c", PROGRAM, str(folder))
    assert again == value and int(hits) >= 1


def test_command_line_caches_unless_told_not_to(tmp_path):
    demo = ["-m", "jaxiso.cli", "demo", "--names", "sphere"]
    off, on = tmp_path / "off", tmp_path / "on"
    off.mkdir()
    _run(*demo, "--no-cache", env=dict(os.environ, JAXISO_CACHE_DIR=str(off)))
    assert not _entries(off)
    _run(*demo, env=dict(os.environ, JAXISO_CACHE_DIR=str(on)))
    assert _entries(on)
