"""Validation of the inverse methods against recordings with known motion (``meniscope validate``)."""
