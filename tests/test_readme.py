"""The README's Python example runs as written, in a fresh interpreter, and makes progress."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def readme_python_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), flags=re.S)


def test_readme_example_optimizes_and_exits(tmp_path):
    """The example's optimize line makes passes (its budget counts the search, not the
    compiling), it saves its tree, and the interpreter exits when its last line is done
    (no compile left running in the background)."""
    blocks = readme_python_blocks()
    assert len(blocks) == 1
    script = tmp_path / "readme_example.py"
    script.write_text(blocks[0] + "\nimport time\nprint('LAST', time.time(), flush=True)\n")
    import time

    done = subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True,
                          timeout=600)
    ended = time.time()
    assert done.returncode == 0, done.stderr[-3000:]
    passes = re.search(r"^(\d+) passes: SAH ([\d.]+)", done.stdout, flags=re.M)
    assert passes and int(passes.group(1)) >= 1, done.stdout
    sah_line = re.search(r"^SAH ([\d.]+)", done.stdout, flags=re.M)
    assert float(passes.group(2)) < float(sah_line.group(1))  # the optimizer improved the tree
    assert (tmp_path / "spot.npz").exists()
    last = float(re.search(r"^LAST ([\d.]+)", done.stdout, flags=re.M).group(1))
    assert ended - last < 30  # generous on a loaded machine; bench/bench_compile.py times it
    assert "warning" not in done.stderr.lower(), done.stderr
