"""Failure anatomy: why each trial ended as it did, read from its records."""
