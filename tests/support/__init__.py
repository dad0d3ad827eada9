"""Helpers shared by every test package: statistics, waiting, concurrent store claimers."""
