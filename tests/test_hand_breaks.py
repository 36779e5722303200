"""scripts/hand_breaks.py's named breaks still apply to the code (issue 61 item 4): each edit's text is
in its file exactly once, so the script breaks what it says. Running them is not part of the suite
(minutes each): docs/results/testing.md has their results and the command."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "scripts"))
import hand_breaks  # noqa: E402


def test_every_break_names_one_line_of_the_current_code():
    assert len({b.name for b in hand_breaks.BREAKS}) == len(hand_breaks.BREAKS) >= 14
    for b in hand_breaks.BREAKS:
        text = (ROOT / b.path).read_text()
        assert text.count(b.old) == 1 and b.new != b.old and "\n" not in b.old, b.name


def test_a_break_is_applied_to_a_copy_once(tmp_path):
    b = hand_breaks.BREAKS[0]
    (tmp_path / b.path).parent.mkdir(parents=True)
    (tmp_path / b.path).write_text((ROOT / b.path).read_text())
    hand_breaks.apply(tmp_path, b)
    assert b.new in (tmp_path / b.path).read_text() and b.old not in (tmp_path / b.path).read_text()
    with pytest.raises(ValueError, match="holds 0 copies"):
        hand_breaks.apply(tmp_path, b)
