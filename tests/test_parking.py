"""The earlier round's landmarks set aside on disk while a run rebuilds (decod_rs.parking)."""

from __future__ import annotations

from pathlib import Path

import pytest

from decod_rs import _core, synthetic_landmark
from decod_rs.parking import set_aside
from decod_rs.stages.extract import SubmapLandmarks


def _landmarks() -> list[_core.Landmark]:
    return [synthetic_landmark(1, j, stamp=10.0 * j, view_seed=j) for j in range(4)]


def test_landmarks_wait_on_disk_and_come_back_bit_for_bit() -> None:
    round_one = _landmarks()
    memo = list(round_one)  # a pair memo holds its own list of the same landmarks
    before = [lm.to_json() for lm in round_one]
    with set_aside([round_one, memo]):
        assert round_one == [] and memo == []
    assert [lm.to_json() for lm in round_one] == before
    assert [lm.to_json() for lm in memo] == before
    assert all(a is b for a, b in zip(round_one, memo, strict=True))


def test_they_come_back_when_the_rebuilt_round_fails() -> None:
    round_one = _landmarks()
    with pytest.raises(RuntimeError, match="rebuild failed"), set_aside([round_one]) as parked:
        parked.leave()  # even where the round had been kept
        raise RuntimeError("rebuild failed")
    assert len(round_one) == 4 and not parked.on_disk


def test_a_round_replaced_by_a_rebuilt_one_stays_on_disk_until_asked_for() -> None:
    first = SubmapLandmarks(landmarks=_landmarks())
    memo = list(first.landmarks)
    before = [lm.to_json() for lm in first.landmarks]
    with set_aside([first.landmarks, memo]) as parked:
        parked.leave()  # the rebuilt round stood
    assert parked.on_disk and first.landmarks == [] and memo == []
    first.parked = parked
    # A replay of the extraction (decod sweep) asks for them: back bit for bit, file gone.
    assert first.restored() is first
    assert [lm.to_json() for lm in first.landmarks] == before
    assert first.parked is None and not parked.on_disk
    assert len(first.restored().landmarks) == 4  # nothing more to read back, nothing doubled


def test_a_round_not_needed_again_is_discarded_unread() -> None:
    round_one = _landmarks()
    with set_aside([round_one]) as parked:
        parked.leave()
    parked.discard()
    parked.restore()  # nothing on disk any more: the list stays empty
    assert round_one == [] and not parked.on_disk


def test_a_full_disk_leaves_them_in_memory_with_a_warning(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def full(path: str, landmarks: list[_core.Landmark]) -> None:
        raise OSError(28, "No space left on device", path)

    monkeypatch.setattr(_core, "park_landmarks", full)
    round_one = _landmarks()
    with set_aside([round_one]):
        assert len(round_one) == 4
    assert len(round_one) == 4
    assert "stays in memory" in capsys.readouterr().err


def test_lists_that_do_not_hold_the_same_landmarks_are_refused() -> None:
    a, b = _landmarks(), _landmarks()
    with pytest.raises(ValueError, match="same landmarks"), set_aside([a, b[:2]]):
        pass
    assert len(a) == 4


def test_a_damaged_file_is_refused_naming_it(tmp_path: Path) -> None:
    path = tmp_path / "landmarks.park"
    _core.park_landmarks(str(path), _landmarks())
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(_core.DatabaseError, match=r"landmarks\.park"):
        _core.unpark_landmarks(str(path))
