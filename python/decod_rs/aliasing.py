"""An aliased corridor: boundaries that truly repeat (beyond the paper).

Where boundaries look alike, a query's best candidate and its runner-up (another physical
boundary) both match beyond chance and the query is ``not_unique``. In a segmental or arched
tunnel neighbouring rings share their structure but are not identical: the best still leads,
by about a third of its inliers. Where the joints are identical, the runner-up is as good as
the best (the view distance decides which one wins), and a query that looks unique is most
likely a repeat whose twin the database does not hold; the consistency selection cannot tell
either, since wrong loops one or two joint spacings off agree with each other.

So a corridor is *aliased* when, among its ambiguous queries (``not_unique``: best and
runner-up both beyond chance, the best not significantly ahead), the share of *near ties*
(the runner-up has at least :data:`NEAR_TIE` of the best's inliers) is at least
:data:`ALIASED_NEAR_TIE_SHARE`, over at least :data:`ALIASED_MIN_QUERIES` of them; an aliased
corridor keeps no loop (reason ``aliased``, :func:`decod_rs.selection.drop_if_aliased`),
within a run and against a survey. Measured on the simulated corridors, every round of a
run (the first and the rebuilt one):

- pipe with identical joints, 30 m, 2 and 3 m of drift, auto: 0.43-0.55 near ties (77-125
  ambiguous queries), the matrix cell 0.47-0.54. Before this rule (and the one on single
  detections, :func:`decod_rs.selection.drop_if_untracked`) 6 of 40 such runs (10 seeds x
  2 drifts x auto and the pipe preset) kept wrong loops, 4-17 each, all one or two joint
  spacings off; with both, none;
- every other cell of the generalisation matrix with 30 or more ambiguous queries (shield
  tunnels with 64 beams and the forward sensor, the horseshoe with 16 beams, uneven drift
  included): at most 0.26, in the first round of a 64-beam shield run under uneven drift
  (its smeared submaps); at most 0.23 in the final rounds.

The median ratio separates less (0.86-0.97 against up to 0.83 in that first round). The
share threshold, 0.35, lies between; fewer ambiguous queries say too little (the hume and pe
cells with 1-12 of them range from 0 to 1).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from decod_rs._core import QueryResult

__all__ = [
    "ALIASED_MIN_QUERIES",
    "ALIASED_NEAR_TIE_SHARE",
    "NEAR_TIE",
    "Aliasing",
    "aliasing",
]

#: A near tie: the runner-up has at least this share of the best's inliers.
NEAR_TIE = 0.9
#: Share of near ties among the ambiguous queries from which a corridor is aliased (module
#: docs: 0.43-0.55 with identical joints, at most 0.26 elsewhere).
ALIASED_NEAR_TIE_SHARE = 0.35
#: Ambiguous queries needed to call a corridor aliased (module docs).
ALIASED_MIN_QUERIES = 30


@dataclass(frozen=True)
class Aliasing:
    """The ambiguous queries of a run (``ambiguous``) and how many of them are near ties
    (``near_ties``)."""

    ambiguous: int
    near_ties: int

    @property
    def share(self) -> float:
        return self.near_ties / self.ambiguous if self.ambiguous else 0.0

    @property
    def aliased(self) -> bool:
        return self.ambiguous >= ALIASED_MIN_QUERIES and self.share >= ALIASED_NEAR_TIE_SHARE

    def report(self) -> dict[str, Any]:
        """The ``report.json`` ``aliasing`` section."""
        return {
            "ambiguous_queries": self.ambiguous,
            "near_ties": self.near_ties,
            "near_tie_share": round(self.share, 4),
            "threshold": ALIASED_NEAR_TIE_SHARE,
            "min_queries": ALIASED_MIN_QUERIES,
            "aliased": self.aliased,
        }


def aliasing(results: Sequence[QueryResult]) -> Aliasing:
    """How often the runner-up of an ambiguous query is as good as the best (module docs)."""
    ambiguous = [r for r in results if r.rejection == "not_unique" and r.inliers > 0]
    ties = sum(1 for r in ambiguous if r.runner_up_inliers >= NEAR_TIE * r.inliers)
    return Aliasing(len(ambiguous), ties)
