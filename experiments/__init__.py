"""The paper's experiments end to end: `experiment run` (runner.py) and its REPORT.md (report.py)."""
