"""Pre/post-event deformation workflow (see tiledsm.workflows)."""
