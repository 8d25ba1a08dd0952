"""Deployment configs (Zenoh json5, rig YAML, systemd units), shipped as package data."""
