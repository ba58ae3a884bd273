"""Run folders, summaries and reports."""
