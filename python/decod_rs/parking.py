"""The earlier round's landmarks set aside on disk while a run rebuilds its submaps (beyond
the paper).

A run whose correction stitches its submaps differently enough extracts, matches and
optimises again on them (:mod:`decod_rs.stages.refine`) and keeps the earlier round in case
the rebuilt one does not stand. Its landmarks (about 29 KB each) were held beside the rebuilt
ones and their prepared views: the peak of a long log's run. While the rebuilt round runs they
wait in a temporary file (``decod_rs._core.park_landmarks``, an exact copy), and the
lists that held them are emptied in place; afterwards they are read back into the same lists,
bit for bit, so that the earlier round (and ``decod sweep``, which replays one extraction under
several settings) finds them as they were. 400 m of pipe: ``docs/measurements.md``, "Long
logs"."""

from __future__ import annotations

import sys
import tempfile
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from decod_rs import _core
from decod_rs._core import Landmark


@contextmanager
def set_aside(holders: Sequence[list[Landmark]]) -> Iterator[None]:
    """Within the block, the landmarks of ``holders`` (lists holding the same landmarks, in
    the same order: a round's landmarks and its pair memo's) are on disk and the lists empty;
    on leaving it, however it is left, the lists hold them again. Where the file cannot be
    written (a full disk) they stay in memory, as before, with a warning."""
    if not holders or not holders[0]:
        yield
        return
    landmarks = list(holders[0])
    if any(list(h) != landmarks for h in holders[1:]):
        raise ValueError("set_aside: the lists do not hold the same landmarks")
    with tempfile.TemporaryDirectory(prefix="decod-park-") as tmp:
        path = Path(tmp) / "landmarks.park"
        try:
            _core.park_landmarks(str(path), landmarks)
            parked = True
        except OSError as exc:
            print(f"warning: {path}: {exc}; the earlier round stays in memory", file=sys.stderr)
            parked = False
        if not parked:
            yield
            return
        del landmarks
        for h in holders:
            h.clear()
        try:
            yield
        finally:
            back = _core.unpark_landmarks(str(path))
            for h in holders:
                h.extend(back)
