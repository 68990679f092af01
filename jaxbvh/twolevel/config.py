"""The knobs of the re-braiding top level, as one Config (the command line's options).

:class:`RebraidConfig` holds what :func:`jaxbvh.twolevel.run` and
:func:`jaxbvh.twolevel.run_from` (and ``build``, ``build_from``, their trees) take besides
the object builder: the opening
threshold, the BRef budget, the top level's bins, the overlap tolerance of the
termination test and the paper's estimated primitive counts. Its defaults are the
constants below (the paper's, or ours where it gives none; :mod:`jaxbvh.twolevel.brefs`
re-exports them),
and ``jaxbvh rebraid`` makes its options from it (:class:`jaxbvh.cli.options.ConfigOptions`),
so the command line and the library share one default and one check per knob.
"""

from __future__ import annotations

import dataclasses

from jaxbvh.configs import Checked, integer, knob, optional, real

DEFAULT_THRESHOLD = 0.1  # paper §4.2 / Figure 4
DEFAULT_OVERLAP = 0.1    # ours: "barely overlapping" (the paper gives no number)
DEFAULT_BINS = 16
DEFAULT_ROUNDS = 64      # ours: rounds of opening per top-level node (1: one level of opening per split)


@dataclasses.dataclass(frozen=True)
class RebraidConfig(Checked):
    """Top-level knobs of a re-braided two-level BVH (Benthin et al. 2017).

    ``threshold``: open a BRef wider than this fraction of its segment's largest extent
    (> 0; inf: never, the plain two-level BVH). ``budget``: BRef slots per instance
    (None: the scene's default, :func:`jaxbvh.twolevel.brefs.scene_slots`).
    ``top_bins``: SAH bins per axis of the top-level build. ``overlap``: <= 4 BRefs whose
    boxes overlap by at most this fraction of the shorter extent on some axis stop
    opening. ``rounds``: rounds of opening per top-level node (each round opens the
    candidates that are still wide; 1: the paper's one level per split). ``estimate``:
    the paper's estimated BRef primitive counts instead of exact ones.
    """

    threshold: float = knob(DEFAULT_THRESHOLD, check=real(above=0.0, finite=False), metavar="T",
                            help="open a BRef wider than T of its segment's largest extent (inf: never)")
    budget: float | None = knob(None, check=optional(real(1.0, 2.0 ** 24)), metavar="B", type=float,
                                help="BRef slots per instance (none: the scene's, brefs.scene_slots)")
    top_bins: int = knob(DEFAULT_BINS, check=integer(2), metavar="B", help="bins per axis of the top-level build")
    overlap: float = knob(DEFAULT_OVERLAP, check=real(0.0), metavar="F",
                          help="<= 4 BRefs overlapping by at most F of the shorter extent on some axis stop opening")
    rounds: int = knob(DEFAULT_ROUNDS, check=integer(1), metavar="R",
                       help="most rounds of opening per top-level node (each opens a level of BRefs)")
    estimate: bool = knob(False, help="the paper's estimated BRef primitive counts (off: exact)")

    def options(self) -> dict:
        """This Config as keywords of :func:`jaxbvh.twolevel.run_from` (which also takes the Config itself)."""
        return dataclasses.asdict(self)
