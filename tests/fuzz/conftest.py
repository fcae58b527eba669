"""The fuzz suite's record: how many generated cases ran per property and how each ended."""

from tests.fuzz.harness import summary_lines


def pytest_terminal_summary(terminalreporter):
    lines = summary_lines()
    if lines:
        terminalreporter.write_sep("-", "torchmetal fuzz cases")
        for line in lines:
            terminalreporter.write_line(line)
