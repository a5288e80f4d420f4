"""``flyknot-tools closure-study``: free rays vs the tube at the held end, counted."""

from __future__ import annotations

from flyknot_tools.cli import main
from flyknot_tools.closure_study import study
from tests.test_judging import TRIALS, _record


def test_the_wrap_is_a_near_tie_only_with_free_rays(tmp_path, capsys):
    for name, (stem, knot) in TRIALS.items():
        _record(stem, knot).save(tmp_path / "runs" / "r" / "learning" / name)
    result = study([tmp_path])
    assert result["trials"] == 3
    # The wrap at the grip: 15-16 of 31 with free rays, 31 of 31 with the tube.
    assert result["free"]["13-18"] == 1 and result["free"]["31-31"] == 2
    assert result["tube"]["31-31"] == 3
    assert result["classes"] == {"unknot": 1, "wrapped_at_grip": 1, "knot": 1}
    assert main(["closure-study", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "| free | 0 | 1 | 0 | 0 | 0 | 0 | 2 |" in out
    assert "| tube | 0 | 0 | 0 | 0 | 0 | 0 | 3 |" in out
