"""bench/bench_compile.py measures what it says: one cheap entry, cold then warm.

Not a timing test: it checks that the cold process compiled programs and counted their
size, and that the warm process loaded every one of them from the persistent cache the
cold one filled (the premise of the benchmark's warm column).
"""

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_bench_compile_cold_then_warm(tmp_path):
    out = tmp_path / "compile"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    subprocess.run([sys.executable, str(REPO / "bench" / "bench_compile.py"), "--only", "build:median",
                    "--out", str(out)], env=env, check=True, capture_output=True, timeout=300)
    results = json.loads(out.with_suffix(".json").read_text())
    (row,) = results["rows"]
    cold, warm = row["cold"], row["warm"]
    assert row["name"] == "build:median" and "build:median" in out.with_suffix(".md").read_text()
    assert cold["compiled"] > 0 and cold["compiled"] == sum(not p["hit"] for p in cold["programs"])
    assert cold["ops"] > 0 and cold["ops"] == sum(p["ops"] for p in cold["programs"])
    # every program the cold process sent to XLA is found in the cache by the warm one
    assert warm["compiled"] == 0
    assert warm["hits"] == cold["compiled"] + cold["hits"]
    assert [p["name"] for p in warm["programs"]] == [p["name"] for p in cold["programs"]]
    for run in (cold, warm):
        assert run["cpu"] > 0 and run["import_jax_cpu"] > 0 and run["process_cpu"] >= run["cpu"]
