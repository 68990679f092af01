"""The persistent compilation cache is on by default for library users (jaxbvh.compile_cache).

Each case runs in a fresh interpreter: the cache is process-wide JAX state, set at import.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from helpers import COUNT_COMPILES

# prints what is in force after `import jaxbvh` (and, with "build", what one small build
# compiled or loaded)
_PROBE = """
import json, sys, os
pre = sys.argv[1]
if pre:
    import jax
    jax.config.update("jax_compilation_cache_dir", pre)
import jax.monitoring
""" + COUNT_COMPILES + """import numpy as np
import jaxbvh
out = {"status": jaxbvh.compile_cache.status(), "dir": jax.config.jax_compilation_cache_dir,
       "min_secs": jax.config.jax_persistent_cache_min_compile_time_secs}
if "build" in sys.argv[2:]:
    lo = np.arange(12, dtype=np.float32).reshape(4, 3)
    jax.block_until_ready(jaxbvh.build(lo, lo + 1, method="median"))
    out["compiled"], out["hits"] = len(compiles) - len(hits), len(hits) + len(stored)
if "disable" in sys.argv[2:]:
    jaxbvh.compile_cache.disable()
    out["after_disable"] = jax.config.jax_compilation_cache_dir
print("PROBE" + json.dumps(out))
"""


def _probe(env_changes: dict, *args: str, pre: str = "") -> dict:
    env = {k: v for k, v in os.environ.items()
           if k not in ("JAXBVH_CACHE_DIR", "JAXBVH_CACHE", "JAX_COMPILATION_CACHE_DIR", "XDG_CACHE_HOME")}
    env.update(env_changes)
    done = subprocess.run([sys.executable, "-c", _PROBE, pre, *args], env=env, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    line = [x for x in done.stdout.splitlines() if x.startswith("PROBE")][-1]
    return json.loads(line[len("PROBE"):])


def test_on_by_default_in_the_per_user_folder_and_a_second_process_compiles_nothing(tmp_path):
    """`import jaxbvh` turns the cache on in $XDG_CACHE_HOME/jaxbvh/jax with every program
    cached; a second process loads the programs instead of compiling them."""
    env = {"XDG_CACHE_HOME": str(tmp_path / "xdg"), "HOME": str(tmp_path / "home")}
    folder = tmp_path / "xdg" / "jaxbvh" / "jax"
    first = _probe(env, "build")
    assert first["status"] == {"folder": str(folder), "owner": "jaxbvh"}
    assert first["min_secs"] == 0.0 and first["compiled"] > 0
    assert any(folder.iterdir())
    second = _probe(env, "build")
    assert second["compiled"] == 0 and second["hits"] > 0
    assert not (tmp_path / "home").exists()  # nothing written to ~


def test_jaxbvh_cache_dir_moves_it_and_the_switch_turns_it_off(tmp_path):
    moved = _probe({"JAXBVH_CACHE_DIR": str(tmp_path / "moved"), "HOME": str(tmp_path / "home")}, "build",
                   "disable")
    assert moved["status"]["folder"] == str(tmp_path / "moved") and any((tmp_path / "moved").iterdir())
    assert moved["after_disable"] is None  # disable() puts JAX's options back
    for word in ("off", "0", "False"):
        off = _probe({"JAXBVH_CACHE": word, "JAXBVH_CACHE_DIR": str(tmp_path / word)}, "build")
        assert off["status"] == {"folder": None, "owner": None} and off["dir"] is None
        assert not (tmp_path / word).exists()


def test_a_cache_the_user_configured_in_jax_is_left_alone(tmp_path):
    ours = tmp_path / "ours"
    by_env = _probe({"JAX_COMPILATION_CACHE_DIR": str(tmp_path / "theirs"), "JAXBVH_CACHE_DIR": str(ours)})
    assert by_env["status"] == {"folder": str(tmp_path / "theirs"), "owner": "user"}
    assert by_env["min_secs"] == 1.0  # JAX's own default, untouched
    by_config = _probe({"JAXBVH_CACHE_DIR": str(ours)}, "build", "disable", pre=str(tmp_path / "mine"))
    assert by_config["status"] == {"folder": str(tmp_path / "mine"), "owner": "user"}
    assert by_config["after_disable"] == str(tmp_path / "mine")  # disable() never touches it
    assert not ours.exists()


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_a_folder_that_cannot_be_made_leaves_the_cache_off(tmp_path):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        out = _probe({"JAXBVH_CACHE_DIR": str(locked / "jax")}, "build")
    finally:
        locked.chmod(0o700)
    assert out["status"]["folder"] is None


def test_a_file_in_the_way_leaves_the_cache_off(tmp_path):
    """The same rule where root runs too: a folder under a file cannot be made."""
    (tmp_path / "file").write_text("x")
    out = _probe({"JAXBVH_CACHE_DIR": str(tmp_path / "file" / "jax")}, "build")
    assert out["status"]["folder"] is None and out["compiled"] > 0
    assert (tmp_path / "file").read_text() == "x"
