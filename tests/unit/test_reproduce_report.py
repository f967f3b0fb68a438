"""The reproduction report's prose is read from its tables, never written once by hand
(the Table IV summary went stale when the table was re-run)."""

from __future__ import annotations

from semservo.reproduce import methods
from semservo.reproduce.report import table4_summary


def _table4(successes: dict[str, list[int]], compute_ms: dict[str, float]) -> dict:
    cases = ["optimal", "noisy"]
    rows = {case: {method: [{"outcome": "converged" if trial < successes[method][index] else "diverged",
                             "true_error_px": 0.05, "compute_ms": compute_ms[method], "reason": "lost"}
                            for trial in range(6)]
                   for method in methods.METHODS}
            for index, case in enumerate(cases)}
    return {"cases": cases, "trials": 6, "rows": rows, "at_target_px": 1.0}


def test_the_summary_says_who_computes_less_who_ties_and_that_none_converges_more_often():
    result = _table4({"semservo": [6, 6], "photometric": [2, 6], "dis": [6, 5], "farneback": [3, 3],
                      "sift": [6, 6], "orb": [0, 0]},
                     {"semservo": 2.0, "photometric": 0.4, "dis": 4.0, "farneback": 6.0, "sift": 70.0, "orb": 20.0})
    summary = table4_summary(result)
    # One value, not "0.20-0.20" (nor "0-0 of 1 trials" from --quick).
    assert "photometric DVS computes less per iteration (0.20 x semservo's)" in summary
    assert "2-6 of 6 trials per case, as often as semservo in case 2 only" in summary
    assert "flow: DIS matches semservo's successes in case 1 at 2.0 x its computation" in summary
    assert "SIFT (for SURF) matches semservo's successes in cases 1, 2" in summary
    assert "Farneback" not in summary and "ORB" not in summary  # neither ties semservo anywhere
    assert summary.endswith("No method converges more often.")


def test_the_summary_names_a_method_that_converges_more_often():
    result = _table4({"semservo": [4, 6], "photometric": [2, 2], "dis": [5, 6], "farneback": [0, 0],
                      "sift": [0, 0], "orb": [0, 0]},
                     {"semservo": 2.0, "photometric": 0.4, "dis": 4.0, "farneback": 6.0, "sift": 70.0, "orb": 20.0})
    assert table4_summary(result).endswith("Converging more often than semservo: flow: DIS in case 1.")


def test_progress_off_a_terminal_is_plain_lines_not_a_bar():
    """In a log file a progress bar is a wall of carriage returns: there it is a line at
    most every LINE_EVERY_S and one at the end."""
    import io

    from semservo.reproduce import Progress

    log = io.StringIO()  # not a terminal
    now = [0.0]
    progress = Progress("table4", 4, stream=log)
    progress.clock = lambda: now[0]
    progress.started = progress.last_line = 0.0
    for at, note in ((1.0, "optimal: converged"), (31.0, "noisy: converged"), (40.0, "unstable: failed"),
                     (41.0, "mask: converged")):
        now[0] = at
        progress.step(note)
    progress.close()
    assert "\r" not in log.getvalue()
    assert log.getvalue().splitlines() == ["table4: 2/4 after 31 s, about 31 s left (noisy: converged)",
                                           "table4: 4/4 after 41 s, about 0 s left (mask: converged)"]
