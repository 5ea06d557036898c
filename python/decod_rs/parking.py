"""The earlier round's landmarks set aside on disk while a run rebuilds its submaps (beyond
the paper).

A run whose correction stitches its submaps differently enough extracts, matches and
optimises again on them (:mod:`decod_rs.stages.refine`) and keeps the earlier round in case
the rebuilt one does not stand. Its landmarks (about 29 KB each) were held beside the rebuilt
ones and their prepared views: the peak of a long log's run. While the rebuilt round runs they
wait in a temporary file (``decod_rs._core.park_landmarks``, an exact copy), and the lists
that held them are emptied in place. Where the rebuilt round does not stand, or fails, they
are read back into the same lists, bit for bit. A round whose cells already wait in the
run's spill (:class:`decod_rs._core.Spill`, ``decod run``'s landmarks) holds a few hundred
bytes a landmark and stays as it is. Where it stands, the extraction's own
landmarks stay on disk until something asks for them again (``decod sweep``, which replays one
extraction under several settings: :meth:`decod_rs.stages.extract.SubmapLandmarks.restored`);
on the way back they had made the rest of the run 0.13 GB larger (400 m of pipe:
``docs/measurements.md``, "Long logs")."""

from __future__ import annotations

import sys
import tempfile
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from decod_rs import _core
from decod_rs._core import Landmark

__all__ = ["Parked", "set_aside"]


class Parked:
    """A round's landmarks on disk, the lists that held them empty until :meth:`restore`
    (nothing on disk, and the lists as they were, where the file could not be written)."""

    def __init__(self, holders: Sequence[list[Landmark]]) -> None:
        self._holders = list(holders)
        self._tmp: tempfile.TemporaryDirectory[str] | None = None
        self._left = False
        if not self._holders or not self._holders[0]:
            return
        landmarks = list(self._holders[0])
        if all(lm.on_disk for lm in landmarks):
            return  # their cells already wait in the run's spill: nothing to set aside
        if any(list(h) != landmarks for h in self._holders[1:]):
            raise ValueError("parking: the lists do not hold the same landmarks")
        tmp = tempfile.TemporaryDirectory(prefix="decod-park-")
        path = Path(tmp.name) / "landmarks.park"
        try:
            _core.park_landmarks(str(path), landmarks)
        except OSError as exc:
            tmp.cleanup()
            print(f"warning: {path}: {exc}; the earlier round stays in memory", file=sys.stderr)
            return
        self._tmp = tmp
        for h in self._holders:
            h.clear()

    @property
    def on_disk(self) -> bool:
        """Whether the landmarks wait on disk (their lists empty)."""
        return self._tmp is not None

    def restore(self) -> None:
        """Read the landmarks back into their lists and remove the file (nothing to do when
        they are not on disk)."""
        if self._tmp is None:
            return
        back = _core.unpark_landmarks(str(Path(self._tmp.name) / "landmarks.park"))
        for h in self._holders:
            h.extend(back)
        self.discard()

    def leave(self) -> None:
        """Keep the landmarks on disk past :func:`set_aside`'s block, for whoever holds this to
        :meth:`restore` or :meth:`discard` them."""
        self._left = True

    @property
    def left(self) -> bool:
        """Whether :meth:`leave` was called."""
        return self._left

    def discard(self) -> None:
        """Remove the file without reading it back: the round is not needed again."""
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None


@contextmanager
def set_aside(holders: Sequence[list[Landmark]]) -> Iterator[Parked]:
    """Within the block, the landmarks of ``holders`` (lists holding the same landmarks, in the
    same order: a round's landmarks and its pair memo's) are on disk and the lists empty. On
    leaving it the lists hold them again, however it is left, unless the block ended normally
    after :meth:`Parked.leave` on the :class:`Parked` it was given. Where the file cannot be
    written (a full disk) they stay in memory, as before, with a warning."""
    parked = Parked(holders)
    try:
        yield parked
    except BaseException:
        parked.restore()
        raise
    if not parked.left:
        parked.restore()
