"""docs/validation/<study>.md is what ``python -m validation.reports`` makes of the study's
result file: a report edited by hand, or a result file changed without its report, fails here."""

from __future__ import annotations


def test_every_report_is_its_result_files(validation):
    reports = validation("reports")
    for path, text in reports.documents().items():
        assert path.is_file() and path.read_text() == text, f"{path.name} drifted: python -m validation.reports"


def test_a_report_states_question_command_result_and_verdict(validation):
    reports = validation("reports")
    text = reports.report(reports.STUDIES[0])
    for part in ("**Question.**", "**Command.**", "**Result.**", "**Verdict.**", "| case |"):
        assert part in text
