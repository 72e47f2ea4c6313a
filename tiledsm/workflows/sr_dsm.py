"""Super-resolution before matching: the SR -> DSM comparison workflow (see tiledsm.workflows)."""
