"""Log tools: replay, report, export."""
