"""Start-up of the command line for what needs no JAX: ``--help``, ``--version``, usage errors.

Each command line runs as a whole process (the installed ``jaxbvh`` console script, or
``python -c`` through :func:`jaxbvh.cli.front.main` with ``--python``), ``--repeats``
times; the table gives the least and the median wall seconds and whether the process
imported JAX. The front (:mod:`jaxbvh.cli.front`) answers these from the parsers'
description without importing JAX; target (issue "A first run that works"): under
0.3 s. The slow path the front replaced (the whole tool imported to build the parsers)
is timed beside it (``jaxbvh.cli.app.main``).

Run: ``python bench/bench_cli_start.py [--repeats 5]``; results in
``bench/results/cli_start.{json,md}``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
CASES = [["--help"], ["--version"], ["build", "--help"], ["build", "--bins", "many"], ["frobnicate"]]
_ENTRY = {"front": "from jaxbvh.cli.front import main", "whole tool": "from jaxbvh.cli.app import main"}
_PROBE = "import sys\n{entry}\nstatus = main(sys.argv[1:])\nsys.stderr.write('JAX %s\\n' % ('jax' in sys.modules))\n" \
         "sys.exit(status)"


def time_case(entry: str, argv: list[str], repeats: int) -> dict:
    times, jax_loaded, status = [], None, None
    code = _PROBE.format(entry=_ENTRY[entry])
    for _ in range(repeats):
        started = time.perf_counter()
        done = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, timeout=120,
                              env=dict(os.environ, PYTHONPATH=str(ROOT)))
        times.append(time.perf_counter() - started)
        status = done.returncode
        jax_loaded = "JAX True" in done.stderr
    return {"entry": entry, "argv": " ".join(argv), "status": status, "jax_imported": jax_loaded,
            "min_s": min(times), "median_s": statistics.median(times)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    rows = [time_case(entry, argv, args.repeats) for argv in CASES for entry in _ENTRY]
    load = os.getloadavg()
    out = {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "python": platform.python_version(),
           "machine": f"{platform.machine()}, {os.cpu_count()} cores", "load": load, "repeats": args.repeats,
           "rows": rows}
    lines = ["# Command-line start-up without JAX", "",
             f"`python bench/bench_cli_start.py --repeats {args.repeats}`; {out['date']}; {out['machine']}; "
             f"Python {out['python']}; load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}. Whole processes "
             "(`python -c`, no shell shim); least and median wall seconds of the repeats.", "",
             "| command line | entry | exit | JAX imported | min s | median s |", "|---|---|---:|---|---:|---:|"]
    for r in rows:
        lines.append(f"| `jaxbvh {r['argv']}` | {r['entry']} | {r['status']} | {'yes' if r['jax_imported'] else 'no'} "
                     f"| {r['min_s']:.2f} | {r['median_s']:.2f} |")
    RESULTS.mkdir(parents=True, exist_ok=True)
    for suffix, text in ((".json", json.dumps(out, indent=1) + "\n"), (".md", "\n".join(lines) + "\n")):
        path = RESULTS / f"cli_start{suffix}"
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(text)
        tmp.replace(path)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
