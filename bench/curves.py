"""What the optimizer benches share: timed SAH-against-time curves and their plots.

``bench/bench_optimize.py`` and ``bench/bench_quality.py`` both run every optimizer twice
on one input: once to compile (:func:`warm_up`), then timed with an ``on_step`` callback
(:func:`timed_curve`: the SAH after every step against wall seconds since the call
began), and draw one panel per input with a step curve per method (:func:`draw_curves`).

The warm-up runs under a time budget, as the timed run does, and is stopped from the
host after its first chunk: every run compiles its loop of steps *and* ``result`` before
its search (``jaxbvh.optimize.driver.compile_loop``), and both are then cached in the
process. (Before that was so, a warm-up cut after its first step never compiled
``result``: the timed run then compiled it inside its own clock, 2 – 3 s of the
pipeline's "time to quality" on legocar in the first round of issue 19's bench.)
"""

from __future__ import annotations

import sys
import time

import numpy as np

from jaxbvh.optimize import OPTIMIZERS, optimize

#: the warm-up's time budget: large enough that compiling never runs it out
WARM_UP_BUDGET = 3600.0


class _FirstChunk(Exception):
    """Raised by the warm-up's ``on_step`` to end it after its first chunk."""


def _stop(info):
    raise _FirstChunk


def warm_up(tree, method: str, **options) -> float:
    """Compile every program a budgeted run of ``method`` on ``tree`` uses; seconds taken
    (compiling, ``init`` and one step: the cold cost)."""
    started = time.perf_counter()
    try:
        optimize(tree, method, time_budget=WARM_UP_BUDGET, on_step=_stop, **options)
    except _FirstChunk:
        pass
    return time.perf_counter() - started


def timed_curve(tree, method: str, budget: float | None = None, **options):
    """A timed run: ``(result, seconds, curve)``; ``curve``: ``[(seconds, sah, stage), ...]``
    after every step, seconds since the call began (the driver reports after each chunk
    of steps, so points can come in bursts)."""
    curve = []
    start = time.perf_counter()

    def on_step(info):
        curve.append((time.perf_counter() - start, info.sah, info.stage))

    result = optimize(tree, method, time_budget=budget, on_step=on_step, **options)
    return result, time.perf_counter() - start, curve


def pyplot():
    """matplotlib's pyplot on the Agg backend, or None (and why, on stderr)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:
        print(f"no plot: {exc}", file=sys.stderr)
        return None
    return plt


def panels(plt, count: int, cols: int, size: tuple[float, float]):
    """A figure of ``count`` panels, ``cols`` a row: ``(figure, axes [count])``; the unused
    panels are switched off."""
    cols = min(cols, count)
    rows = (count + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(size[0] * cols, size[1] * rows), squeeze=False)
    for ax in axes.ravel()[count:]:
        ax.axis("off")
    return fig, list(axes.ravel()[:count])


def draw_curves(ax, rows, title: str, fontsize: float = 7) -> float:
    """One panel: a step curve per row (``method``, ``sah``, ``start_sah``, ``curve``) on a
    log time axis from 1 ms; returns the lowest SAH drawn (for the caller's y range)."""
    order = list(OPTIMIZERS)  # one colour per method in every panel, legends in one order
    for r in sorted(rows, key=lambda r: order.index(r["method"]) if r["method"] in order else len(order)):
        t = [1e-3] + [max(x, 1e-3) for x, _, _ in r["curve"]]
        s = [r["start_sah"]] + [y for _, y, _ in r["curve"]]
        colour = f"C{order.index(r['method'])}" if r["method"] in order else None
        ax.step(np.maximum(t, 1e-3), s, where="post", color=colour, label=f"{r['method']} ({r['sah']:.3f})")
    ax.set_xscale("log")
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("seconds (warm)")
    ax.set_ylabel("SAH")
    return min(min([y for _, y, _ in r["curve"]] + [r["sah"]]) for r in rows)


def save(fig, path, dpi: int, title: str = "") -> None:
    """Lay the figure out and write it to ``path``."""
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
