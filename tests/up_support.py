"""Helpers of the tests that run `bagit up` as a subprocess (`bagit.harness`, shared with the probes)."""

from bagit.harness import ALL, ENV, alive, rig_up, start_up, up_log, wait_status  # noqa: F401 - re-exported for the tests
