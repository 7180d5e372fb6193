"""Reports of a run: report.json and report.md with the paper's Table I, the self-contained
report.html, and CI gates on a report's summary."""
