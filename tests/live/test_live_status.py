"""What the page says to do next, from the photos' statuses."""
from __future__ import annotations


def test_the_hints_count_the_failures_in_a_row():
    from stereoseed.live.status import FAILURES_IN_A_ROW, page_state

    class Model:  # what page_state reads of a reconstruction: reports and views
        def __init__(self, statuses):
            self.statuses = statuses
            self.views = [type("V", (), {"registered": s != "failed", "flag_reason": None})() for s in statuses]

        def reports(self):
            return [{"image": f"{i}.png", "status": s, "reason": "why" if s == "failed" else None}
                    for i, s in enumerate(self.statuses)]

    names = [f"{i}.png" for i in range(8)]
    ok = ["calibrated", "calibrated pair", "registered", "registered"]
    hints = " ".join(page_state(Model(ok + ["failed"]), names[:5], with_figure=False)["hints"])
    assert "Move back towards the last good view, 3.png" in hints and "in a row" not in hints
    fails = ok + ["failed"] * FAILURES_IN_A_ROW
    hints = page_state(Model(fails), names[:len(fails)], with_figure=False)["hints"]
    assert hints[0].startswith(f"{FAILURES_IN_A_ROW} photos in a row did not register") and "3.png" in hints[0]
    assert "Good: take the next photo" in page_state(Model(ok), names[:4], with_figure=False)["hints"][-1]
