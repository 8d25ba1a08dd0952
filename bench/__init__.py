"""Benchmarks behind `bagit bench`: each prints numbers, none is a pass/fail test."""
