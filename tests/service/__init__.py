"""Tests of the job store, lease queue, worker loop, dataset storage and local runner."""
