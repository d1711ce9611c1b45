"""An opt-in persistent compilation cache: XLA's compiled programs are kept on disk, so a
later process skips the compile of every program an earlier one built (the first picture
of the same scene kind comes sooner). Off unless `enable_cache` is called; the
``jaxiso`` command line turns it on (``--no-cache`` turns it off).

The cache is JAX's own (``jax_compilation_cache_dir``); entries are keyed by the program,
the jax version and the device, so a stale entry is never used. Trust the folder as you
trust code: whoever can write there can make this process run what they wrote.
"""

from __future__ import annotations

import os

import jax


def default_cache_dir(environ=None) -> str:
    """``$JAXISO_CACHE_DIR``, else ``$XDG_CACHE_HOME/jaxiso/xla``, else
    ``~/.cache/jaxiso/xla``."""
    environ = os.environ if environ is None else environ
    if environ.get("JAXISO_CACHE_DIR"):
        return environ["JAXISO_CACHE_DIR"]
    base = environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "jaxiso", "xla")


def enable_cache(dir: str | os.PathLike | None = None) -> str:  # noqa: A002
    """Keeps every compiled program of this process in the folder `dir` (default
    `default_cache_dir()`; made if missing) and reads them back instead of compiling.
    Small and quick compiles are kept too (JAX keeps only those over a second by default).
    Returns the folder's absolute path. Calling it again with another folder switches."""
    path = os.path.abspath(os.path.expanduser(os.fspath(default_cache_dir()
                                                        if dir is None else dir)))
    os.makedirs(path, exist_ok=True)
    if jax.config.jax_compilation_cache_dir not in (None, path):
        from jax.experimental.compilation_cache import compilation_cache

        compilation_cache.reset_cache()  # JAX opens its cache once; forget the old folder
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)  # no size floor
    return path
